"""lab.gauss_seidel: a NumPy replica of the solver's projected Gauss-Seidel on recorded steps."""

from __future__ import annotations

import numpy as np
import pytest

from commands import main
from training.contact_graph import build_graph_set
from lab.gauss_seidel import Steps, gauss_seidel
from training.graph_loss import colour_points


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Builtin's first 60 steps of one thesis world: the bodies land and pile up."""
    path = tmp_path_factory.mktemp("replica") / "val.h5"
    assert main(["generate", "--steps", "60", "--seeds", "3", "--out", str(path), "--quiet"]) == 0
    return path


def test_the_replica_stops_about_where_the_recorded_solve_did(recorded):
    p = Steps(build_graph_set(recorded, max_steps=20), mu=0.5)  # the thesis world's friction
    lam, sweeps = gauss_seidel(p, colour_points(p.ends, p.inverse, seed=0), threshold=1e-4, max_sweeps=1000)
    correction = np.sqrt(np.mean(np.sum((p.solution - p.builtin) ** 2, axis=1)))
    assert np.sqrt(np.mean(np.sum((lam - p.solution) ** 2, axis=1))) < 0.2 * correction
    assert sweeps.shape == (p.n_steps,) and (sweeps >= 1).all() and sweeps.max() > 1
    assert (lam[:, 0] >= 0).all() and (np.abs(lam[:, 1]) <= 0.5 * lam[:, 0] + 1e-12).all()  # inside the cones


def test_a_solve_already_at_its_answer_stops_at_once(recorded):
    p = Steps(build_graph_set(recorded, max_steps=20), mu=0.5)
    colour = colour_points(p.ends, p.inverse, seed=0)
    lam, _ = gauss_seidel(p, colour, threshold=1e-6, max_sweeps=5000)
    again, sweeps = gauss_seidel(p, colour, threshold=1e-4, max_sweeps=1000, start=lam)
    assert (sweeps == 1).all() and np.allclose(again, lam, atol=1e-4)


def test_some_steps_are_a_problem_of_their_own(recorded):
    gs = build_graph_set(recorded, max_steps=20)
    whole, part = Steps(gs, mu=0.5), Steps(gs, mu=0.5, steps=[4, 2])
    assert part.n_steps == 2 and part.step_of.max() == 1
    rows = np.r_[gs.point_offsets[4]:gs.point_offsets[5], gs.point_offsets[2]:gs.point_offsets[3]]
    np.testing.assert_array_equal(part.builtin, whole.builtin[rows])
