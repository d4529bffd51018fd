"""A graph card served with its mirror image: the network asked about the step and about the
step reflected left to right, the mean served (server.mirror_image), on the real shipped
classifier and ONNX Runtime."""

import concurrent.futures
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from deepcontact import wire
from deepcontact.modelcard import ModelCard, ModelCardError
from server.predictors import World
from tests.conftest import reflected

ROOT = Path(__file__).parents[2]
#: The shipped classifier and the same network with its mirror image built into one ONNX graph
#: (python -m training.ensemble --mirror), in the research store.
CLASSIFIER, ENSEMBLE = "graph-face-fr-r12-e15", "graph-face-fr-r12-e15-mirror"


def store_cards(folder: Path) -> None:
    """The classifier and its mirror ensemble from the research store, copied into folder."""
    for name in (CLASSIFIER, ENSEMBLE):
        for suffix in (".json", ".onnx"):
            shutil.copy(ROOT / "lab" / "models" / f"{name}{suffix}", folder)


def alias(folder: Path, name: str, **keys) -> Path:
    path = folder / f"{name}.json"
    path.write_text(json.dumps({"name": name, "alias_of": CLASSIFIER, **keys}))
    return path


def world_of(world_msg) -> World:
    lower, upper, _ = wire.decode_world(world_msg)
    return World((lower, upper), wire.decode_physics(world_msg))


def test_a_mirrored_card_answers_as_the_mirror_ensemble_built_into_one_graph(tmp_path, thesis_steps):
    from server.mirror_image import MirroredGraphPredictor
    from server.predictors import GraphPredictor, load_model

    store_cards(tmp_path)
    mirrored = load_model(alias(tmp_path, "modes-mirror", mirror=True))
    ensemble = load_model(tmp_path / f"{ENSEMBLE}.json")
    plain = load_model(tmp_path / f"{CLASSIFIER}.json")
    assert isinstance(mirrored, MirroredGraphPredictor) and type(plain) is GraphPredictor
    world_msg, steps = thesis_steps
    world = world_of(world_msg)
    spare = concurrent.futures.ThreadPoolExecutor(1)
    for bodies, points in steps:
        mu = np.full(len(points), 0.5, np.float32)
        here = mirrored.predict(bodies, points, world, 0, friction=mu).impulses
        # float32 sums in another order: the same answer to about 1e-6 N s
        np.testing.assert_allclose(here, ensemble.predict(bodies, points, world, 0, friction=mu).impulses, atol=1e-4)
        # The reflected half on another thread: the same numbers to the bit.
        np.testing.assert_array_equal(mirrored.predict(bodies, points, world, 0, friction=mu, spare=spare).impulses,
                                      here)
        # Without its reflected half it is the plain network.
        np.testing.assert_array_equal(mirrored.predict(bodies, points, world, 0, friction=mu, reflected=False).impulses,
                                      plain.predict(bodies, points, world, 0, friction=mu).impulses)
    spare.shutdown()


def test_the_mirrored_answer_to_the_reflected_world_is_its_answer_reflected(tmp_path, thesis_steps):
    from server.predictors import load_model

    store_cards(tmp_path)
    mirrored = load_model(alias(tmp_path, "modes-mirror", mirror=True))
    plain = load_model(tmp_path / f"{CLASSIFIER}.json")
    world_msg, steps = thesis_steps
    world = world_of(world_msg)
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5, np.float32)
    flipped = reflected(bodies, points)
    answer = mirrored.predict(bodies, points, world, 0, friction=mu).impulses
    answer_flipped = mirrored.predict(*flipped, world, 0, friction=mu).impulses
    # Normal impulses the same, tangent ones (along (n_y, -n_x)) negated: the mean is symmetric
    # by construction, where the network alone is not.
    np.testing.assert_allclose(answer_flipped, answer * [1, -1], atol=1e-4)
    alone = plain.predict(bodies, points, world, 0, friction=mu).impulses
    alone_flipped = plain.predict(*flipped, world, 0, friction=mu).impulses
    assert np.abs(alone_flipped - alone * [1, -1]).max() > 1e-2


def test_a_face_route_on_a_mirrored_classifier_runs_the_reflected_half_beside_it(tmp_path, thesis_steps):
    from server.face_route import FaceRoutePredictor
    from server.mirror_image import MirroredGraphPredictor
    from server.predictors import load_model

    store_cards(tmp_path)
    face = {"pressing": 0.75, "rounds": 40, "relax": 1.6, "solver": "dual"}  # the default's, every step served
    route = load_model(alias(tmp_path, "route-mirror", mirror=True, face=face))
    ensemble = tmp_path / "route-ensemble.json"
    ensemble.write_text(json.dumps({"name": "route-ensemble", "alias_of": ENSEMBLE, "face": face}))
    on_ensemble = load_model(ensemble)
    on_plain = load_model(alias(tmp_path, "route", face=face))
    assert isinstance(route, FaceRoutePredictor) and isinstance(route.classifier, MirroredGraphPredictor)
    assert route.compiled
    world_msg, steps = thesis_steps
    world = world_of(world_msg)
    for bodies, points in steps:
        mu = np.full(len(points), 0.5, np.float32)
        answer = route.predict(bodies, points, world, 0, friction=mu)
        assert answer.served_by is None and set(answer.stages) == {"features", "inference", "solve", "admit"}
        np.testing.assert_allclose(answer.impulses, on_ensemble.predict(bodies, points, world, 0, friction=mu).impulses,
                                   atol=1e-3)
        # A server answering more steps than it has cores: the step's half alone, as the plain
        # classifier's route.
        busy = route.predict(bodies, points, world, 0, friction=mu, deadline=1e12, slowdown=1.5)
        assert busy.served_by is None
        np.testing.assert_array_equal(busy.impulses, on_plain.predict(bodies, points, world, 0, friction=mu).impulses)


def test_mirror_is_a_graph_cards_yes_or_no_and_an_alias_may_set_it(tmp_path):
    store_cards(tmp_path)
    card = json.loads((tmp_path / f"{CLASSIFIER}.json").read_text())
    assert ModelCard.from_dict(card).mirror is False
    assert ModelCard.load(alias(tmp_path, "modes-mirror", mirror=True)).mirror is True
    with pytest.raises(ModelCardError, match="mirror 'yes': true or false"):
        ModelCard.from_dict({**card, "mirror": "yes"})
    with pytest.raises(ModelCardError, match="only a graph model"):
        ModelCard.from_dict({**card, "kind": "pressure", "mirror": True})
