"""`deepcontact generate` and the HDF5 data set it writes."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

from deepcontact import dispatch
from commands import main
from training.dataset import Dataset, DatasetError, Writer, differences

SMALL = ["--steps", "60", "--seeds", "1-3", "--quiet"]


def generate(path, *extra):
    return main(["generate", "--out", str(path), *SMALL, *extra])


def test_generate_records_every_step_and_reads_back_a_step_at_a_time(tmp_path):
    out = tmp_path / "train.h5"
    assert generate(out) == 0
    with Dataset(out) as ds:
        assert ds.seeds == [1, 2, 3] and ds.scene["steps"] == 60
        assert len(ds) == 180
        assert list(ds.steps["seed"][::60]) == [1, 2, 3]
        bodies, points, row = ds.step(59)
        assert len(bodies) == 101 and len(points) == row["point_count"] > 0
        assert np.isfinite(points["impulse"]).all()
        assert ds.trace(59).shape == (row["velocity_iterations"],)
        batches = list(ds.batches(16, seed=1))
        assert sum(len(b) for b in batches) == int((ds.steps["point_count"] > 0).sum())
        assert [len(b) for b in ds.batches(16, seed=1)] == [len(b) for b in batches]
    with h5py.File(out) as f:
        assert f["points"].compression == "gzip" and f["points"].chunks is not None


def test_contents_do_not_depend_on_the_number_of_processes(tmp_path):
    one, two = tmp_path / "one.h5", tmp_path / "two.h5"
    assert generate(one, "--workers", "1") == 0
    assert generate(two, "--workers", "2") == 0
    assert differences(one, two) == []  # all but the wall-clock solve_ms, bit for bit


def test_a_faster_compression_writes_the_same_simulations(tmp_path):
    gzip, lzf, none = tmp_path / "gzip.h5", tmp_path / "lzf.h5", tmp_path / "none.h5"
    assert generate(gzip, "--workers", "1") == 0
    assert generate(lzf, "--workers", "1", "--compression", "lzf") == 0
    assert generate(none, "--workers", "1", "--compression", "none") == 0
    assert differences(gzip, lzf) == [] and differences(gzip, none) == []
    with h5py.File(lzf) as f, h5py.File(none) as g:
        assert f["points"].compression == "lzf" and g["points"].compression is None


def test_an_unknown_compression_is_refused(tmp_path):
    with pytest.raises(ValueError, match="zstd"):
        Writer(tmp_path / "x.h5", scene={}, seeds=[1], command="test", compression="zstd")


def test_a_local_ray_writes_what_the_process_pool_writes(tmp_path, capsys):
    pool, ray = tmp_path / "pool.h5", tmp_path / "ray.h5"
    assert generate(pool, "--workers", "2") == 0
    assert generate(ray, "--ray", "--workers", "2") == 0  # a Ray with 2 CPUs started for the run
    assert "a local Ray with 2 CPUs" in capsys.readouterr().out
    assert differences(pool, ray) == []


def test_a_simulation_whose_ray_worker_dies_once_runs_again(tmp_path, monkeypatch, ray_cluster):
    monkeypatch.setenv(dispatch.TEST_KILL_TASK, "seed 2")
    monkeypatch.setenv(dispatch.TEST_KILL_ONCE, str(tmp_path / "killed"))
    reference, out = tmp_path / "reference.h5", tmp_path / "train.h5"
    assert generate(out, "--ray", ray_cluster) == 0
    assert (tmp_path / "killed").exists()  # the first attempt did die
    monkeypatch.delenv(dispatch.TEST_KILL_TASK)
    assert generate(reference, "--workers", "1") == 0
    assert differences(reference, out) == []


@pytest.mark.parametrize("where", ["ray", "pool"])
def test_a_seed_that_fails_is_named_and_nothing_is_written(tmp_path, monkeypatch, capsys, request, where):
    monkeypatch.setenv(dispatch.TEST_KILL_TASK, "seed 3")  # every attempt dies
    out = tmp_path / "train.h5"
    backend = ["--ray", request.getfixturevalue("ray_cluster")] if where == "ray" else ["--workers", "2"]
    assert generate(out, *backend) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "seed 3" in err and "died" in err and "nothing written" in err
    assert list(tmp_path.iterdir()) == []  # no file under the final name, no temporary left behind


def test_ray_missing_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(__import__("sys").modules, "ray", None)  # as if not installed: import fails
    assert generate(tmp_path / "x.h5", "--ray") == 2
    assert "pip install '.[ray]'" in capsys.readouterr().err


def test_benchmark_and_reserved_seeds_are_refused_for_training(tmp_path, capsys):
    out = tmp_path / "x.h5"
    assert main(["generate", "--out", str(out), "--seeds", "899-901", "--quiet"]) == 2
    assert "benchmark" in capsys.readouterr().err and not out.exists()
    assert main(["generate", "--out", str(out), "--seeds", "10000", "--quiet"]) == 2
    assert main(["generate", "--out", str(out), "--seeds", "900", "--steps", "5", "--quiet",
                 "--allow-bench-seeds"]) == 0


def test_existing_output_is_kept_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "train.h5"
    out.write_bytes(b"precious")
    assert generate(out) == 2
    assert out.read_bytes() == b"precious" and "--overwrite" in capsys.readouterr().err
    assert generate(out, "--overwrite") == 0
    assert Dataset(out).seeds == [1, 2, 3]


def test_bad_scene_fails_before_any_work(tmp_path, capsys):
    assert generate(tmp_path / "x.h5", "--bodies", "5000") == 2
    assert "no room" in capsys.readouterr().err


def test_an_interrupted_write_leaves_nothing_under_the_final_name(tmp_path):
    out = tmp_path / "train.h5"
    with pytest.raises(KeyboardInterrupt):
        with Writer(out, scene={}, seeds=[1], command="test"):
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_missing_or_foreign_files_get_a_clear_error(tmp_path):
    with pytest.raises(DatasetError, match="no such data file"):
        Dataset(tmp_path / "none.h5")
    (tmp_path / "junk.h5").write_text("not hdf5")
    with pytest.raises(DatasetError, match="not an HDF5 file"):
        Dataset(tmp_path / "junk.h5")


def test_the_oracle_is_recorded_beside_the_points_and_trains_residual_models(tmp_path):
    from deepcontact.channels import channel_values
    from simclient.scene import SceneSpec, build_world
    from training.dataset import Dataset
    from training.grids import iter_steps

    out = tmp_path / "oracle.h5"
    assert main(["generate", "--seeds", "3", "--steps", "80", "--oracle", "--out", str(out), "--quiet"]) == 0
    with Dataset(out) as ds:
        assert ds.has_oracle
        rows = np.flatnonzero(ds.steps["point_count"] > 0)
        steps = ds.steps
    # Step k's oracle is the engine's own, taken before that step was solved.
    k = int(rows[-1])
    engine = build_world(dataclasses.replace(SceneSpec.thesis(), steps=80), 3)
    for _ in range(k):
        engine.step()
    engine.collide()
    expected = engine.oracle()
    step = dict(iter_steps(out, steps, np.array([k])))[k]
    np.testing.assert_array_equal(step.oracle, expected)
    assert step.previous is not None and len(step.previous) == steps["point_count"][k - 1]
    correction = channel_values(["oracle_correction_normal"], step)[:, 0]
    np.testing.assert_allclose(correction, expected[:, 0] - step.contacts["builtin"][:, 0], rtol=1e-6)


def test_a_zoo_world_is_recorded_with_each_seeds_physics_and_trains_the_contact_graph(tmp_path):
    from deepcontact.envelope import Envelope
    from simclient import zoo
    from training.contact_graph import GRAPH_TARGETS, build_graph_set
    from training.dataset import trained_on

    out = tmp_path / "jointed.h5"
    assert generate(out, "--world", "simclient.zoo:jointed") == 0
    with Dataset(out) as ds:
        assert ds.scene["kind"] == "world" and sorted(ds.physics) == [1, 2, 3]
        for seed, (dt, gx, gy) in ds.physics.items():
            world, drawn = zoo.jointed(seed)
            assert dt == pytest.approx(drawn) and (gx, gy) == pytest.approx(tuple(world.gravity))
    graphs = build_graph_set(out, inputs=("vn", "vt", "friction"), targets=GRAPH_TARGETS)
    assert graphs.features.shape[1] == 3 and np.isfinite(graphs.features).all()
    # The friction the points carry: the zoo draws one per world, so no point is at the thesis's 0.5.
    assert not np.isclose(graphs.features[:, 2], 0.5).any()
    envelope = Envelope.from_dict(trained_on([out]))
    assert envelope.joints and "other" in envelope.shapes and envelope.dt[0] > 1 / 120 - 1e-9
