"""training.ensemble: several shipped contact-graph models served as one, over a real server."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from deepcontact.modelcard import ModelCard, ModelCardError
from training.card_variant import card_variant
from tests.conftest import reflected
from training.ensemble import agreed_mean, build_ensemble, main

SHIPPED = Path(__file__).parents[2] / "lab" / "models"  # the research store
MEMBERS = ("graph-projected-max-1-799", "graph-projected-max-1-799-pooled")  # two normalizations, two networks


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """The two members (cards and ONNX files), their ensemble `both`, its `both-t1` card and
    `agreed`, their mean served only where they agree to within half its size."""
    folder = tmp_path_factory.mktemp("ensemble")
    for name in MEMBERS:
        for suffix in (".json", ".onnx"):
            shutil.copy(SHIPPED / f"{name}{suffix}", folder)
    build_ensemble([folder / f"{name}.json" for name in MEMBERS], "both")
    card_variant(folder / "both.json", correction_threshold=1.0)
    build_ensemble([folder / f"{name}.json" for name in MEMBERS], "agreed", agree=0.5)
    return folder


def served(folder: Path, model: str, world, steps) -> list[np.ndarray]:
    """Each step's warm start from a real server on loopback, (P, 2) N s."""
    import grpc

    from deepcontact import wire
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.serve import Server

    server = Server(models=folder).start()
    try:
        with grpc.insecure_channel(server.address) as channel:
            requests = [wire.encode_step(k, model, bodies, points, world=world if k == 0 else None,
                                         builtin=points["builtin"]) for k, (bodies, points) in enumerate(steps)]
            replies = list(pb_grpc.WarmStartStub(channel).Stream(iter(requests)))
    finally:
        server.stop()
    return [np.stack(wire.decode_impulses(reply), axis=1) for reply in replies]


def test_an_ensemble_serves_the_mean_of_its_members_corrections(folder, thesis_steps):
    world, steps = thesis_steps
    builtin = [points["builtin"] for _, points in steps]
    a, b, both, both_t1 = (served(folder, name, world, steps) for name in (*MEMBERS, "both", "both-t1"))
    for k in range(len(steps)):
        mean = ((a[k] - builtin[k]) + (b[k] - builtin[k])) / 2
        np.testing.assert_allclose(both[k], builtin[k] + mean, atol=2e-5)
        # The threshold reads the mean correction, not each member's.
        kept = np.abs(mean[:, 0]) > 1.0
        np.testing.assert_allclose(both_t1[k], builtin[k] + mean * kept[:, None], atol=2e-5)
    assert any((np.abs((x - y)[:, 0]) > 1.0).any() for x, y in zip(both, builtin))  # some points corrected


def test_an_agreeing_ensemble_serves_the_mean_only_where_its_members_agree(folder, thesis_steps):
    world, steps = thesis_steps
    builtin = [points["builtin"] for _, points in steps]
    a, b, agreed = (served(folder, name, world, steps) for name in (*MEMBERS, "agreed"))
    gated = []
    for k in range(len(steps)):
        members = np.stack([a[k] - builtin[k], b[k] - builtin[k]])
        np.testing.assert_allclose(agreed[k], builtin[k] + agreed_mean(members, 0.5), atol=2e-5)
        # Two members agree to within half their mean when they differ by less than their mean.
        mean = members.mean(axis=0)
        far = np.abs(members[0] - members[1]) > 1.1 * np.abs(mean)
        np.testing.assert_array_equal(agreed[k][far], builtin[k][far])
        gated.append(far)
    assert any(g.any() for g in gated) and not all(g.all() for g in gated)
    assert ModelCard.load(folder / "agreed.json").architecture["config"]["agree"] == 0.5
    assert main([*(str(folder / f"{name}.json") for name in MEMBERS), "--name", "none", "--agree", "0"]) == 2
    assert not (folder / "none.onnx").exists()


@pytest.mark.parametrize("member", MEMBERS)  # the second's rounds read its step's mean: it cannot share a batch
def test_a_mirrored_model_serves_the_mean_of_its_answers_to_the_step_and_to_its_mirror_image(
        folder, tmp_path, thesis_steps, member):
    from deepcontact import wire

    build_ensemble([folder / f"{member}.json"], "mirrored", out_dir=tmp_path, mirror=True)
    for suffix in (".json", ".onnx"):
        shutil.copy(folder / f"{member}{suffix}", tmp_path)
    world, steps = thesis_steps
    lower, upper, _ = wire.decode_world(world)
    # The same steps in the world reflected about x = 0, served by the member itself.
    image_world = wire.encode_world((-upper[0], lower[1]), (-lower[0], upper[1]), physics=wire.decode_physics(world))
    image = served(tmp_path, member, image_world, [reflected(bodies, points) for bodies, points in steps])
    plain, mirrored = (served(tmp_path, name, world, steps) for name in (member, "mirrored"))
    back = np.array([1.0, -1.0], np.float32)  # a tangent impulse changes sign under the reflection
    differ = []
    for k in range(len(steps)):
        # Each answer is Box2D's warm start plus a correction: the mean of the two corrections.
        np.testing.assert_allclose(mirrored[k], (plain[k] + image[k] * back) / 2, atol=2e-5)
        differ.append(np.abs(plain[k] - image[k] * back).max())
    assert max(differ) > 0.01  # the network is not symmetric by itself, so the mean is another answer
    card = ModelCard.load(tmp_path / "mirrored.json")
    assert card.architecture["config"]["mirror"] is True and card.commands[-1].endswith("--mirror")
    assert card.parity_max_abs_error < 1e-4


def test_a_second_pass_reads_the_step_at_its_first_pass_warm_start(folder, thesis_steps):
    from deepcontact import wire
    from deepcontact.channels import Step, channel_values
    from server.predictors import GraphPredictor, World

    card = ModelCard.load(card_variant(folder / f"{MEMBERS[0]}.json", passes=2))
    predictor = GraphPredictor(card, card.onnx_path(folder / f"{card.name}.json"))
    seen, infer = [], predictor.infer
    predictor.infer = lambda x, ends, dynamic: seen.append(x.copy()) or infer(x, ends, dynamic)
    world, steps = thesis_steps
    bodies, points = steps[0]
    lower, upper, _ = wire.decode_world(world)
    physics = wire.decode_physics(world)
    answer = predictor.predict(bodies, points, World((lower, upper), physics), 0).impulses
    first, second = (served(folder, name, world, steps[:1])[0] for name in (MEMBERS[0], card.name))
    np.testing.assert_allclose(answer, second, atol=2e-5)  # what a real server serves
    assert np.abs(second - first).max() > 1e-3  # the second pass moved the first's answer
    # The second pass reads every channel at the first pass's warm start, except which
    # points are new to Box2D: that stays what the request said (some are, some are not).
    moved = points.copy()
    moved["builtin"] = first
    inputs = card.gridspec.inputs
    expected = channel_values(inputs, Step(bodies, moved, None, physics))
    new = inputs.index("new_point")
    expected[:, new] = channel_values(("new_point",), Step(bodies, points, None, physics))[:, 0]
    mean, std = card.gridspec.normalization_arrays(inputs)
    assert len(seen) == 2 and len(np.unique(seen[0][:, new])) == 2
    np.testing.assert_allclose(seen[1], (expected - mean) / std, atol=1e-3)
    np.testing.assert_array_equal(seen[1][:, new], seen[0][:, new])


def test_the_ensembles_card_names_its_members_and_folds_their_normalization_into_the_graph(folder):
    card = ModelCard.load(folder / "both.json")
    members = [ModelCard.load(folder / f"{name}.json") for name in MEMBERS]
    assert card.kind == "graph" and card.combine == "residual" and card.gridspec.normalization == {}
    assert card.architecture["config"]["members"] == list(MEMBERS)
    assert card.parameters == sum(m.parameters for m in members)
    assert card.parity_max_abs_error < 1e-4
    assert card.commands[-1].startswith("python -m training.ensemble")  # and the members' own before it
    assert set(members[0].commands + members[1].commands) <= set(card.commands)


def test_an_ensemble_refuses_members_it_cannot_average(folder, tmp_path, capsys):
    for suffix in (".json", ".onnx"):
        shutil.copy(SHIPPED / f"pressure{suffix}", tmp_path)
    with pytest.raises(ModelCardError, match="kind graph, combine residual"):
        build_ensemble([folder / f"{MEMBERS[0]}.json", tmp_path / "pressure.json"], "mixed")
    assert main([str(folder / f"{MEMBERS[0]}.json"), "--name", "alone"]) == 2
    assert "at least two member cards, or one with --mirror" in capsys.readouterr().err
    assert not (folder / "alone.onnx").exists() and not (tmp_path / "mixed.onnx").exists()
