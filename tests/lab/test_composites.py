"""Warm starts over warm starts (lab.composites): trial solves on the same states."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from lab.composites import Pick, sweeps_to_builtin
from lab.oracles import OracleMix
from simclient.provider import Provider, as_warm_start
from simclient.scene import SceneSpec
from simclient.simulate import run_simulation
from simclient.warmstarts import make_provider

SHORT = dataclasses.replace(SceneSpec.thesis(), steps=120)


def mean_iterations(name, spec=SHORT):
    return run_simulation(spec, 901, make_provider(name))["summary"]["mean_velocity_iterations"]


def test_shadow_serves_its_first_candidate_as_it_would_alone_and_prices_builtin_beside_it():
    alone = run_simulation(SHORT, 901, make_provider("jitter@0.01"))
    shadowed = run_simulation(SHORT, 901, make_provider("shadow:jitter@0.01"))
    assert shadowed["per_step"]["velocity_iterations"] == alone["per_step"]["velocity_iterations"]
    its = [i for i, n in zip(alone["per_step"]["velocity_iterations"], alone["per_step"]["contact_points"]) if n]
    assert [t[1] for t in shadowed["trials"]] == its  # builtin's count on the same states is t[0]


def test_price_steps_as_builtin_and_prices_each_candidate_on_builtins_states():
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    jitter = run_simulation(SHORT, 901, make_provider("shadow:jitter@0.01"))
    priced = run_simulation(SHORT, 901, make_provider("price:jitter@0.01"))
    assert priced["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    its = [i for i, n in zip(builtin["per_step"]["velocity_iterations"], builtin["per_step"]["contact_points"]) if n]
    assert [t[0] for t in priced["trials"]] == its  # a trial from builtin's start is the step's own solve
    # the same states in every run: a second run prices the same candidate the same way
    assert run_simulation(SHORT, 901, make_provider("price:jitter@0.01"))["trials"] == priced["trials"]
    assert [t[1] for t in priced["trials"]] != [t[1] for t in jitter["trials"]]  # jitter's own states differ


def test_sweeps_to_builtins_accuracy_count_where_the_cap_hides_a_better_start():
    f = lambda *r: np.array(r, np.float32)  # a trial's residual trace, N s a sweep
    # Builtin converges in 3: every trial is counted by its own iterations under the threshold
    assert sweeps_to_builtin([f(1, 0.1, 1e-5), f(0.5, 5e-5)], threshold=1e-4) == [3, 2]
    # Builtin ends at the cap 0.2 from converged: a start there after one sweep is worth one;
    # one that never gets there counts its sweeps, a lower bound
    assert sweeps_to_builtin([f(1, 0.5, 0.2), f(0.2, 0.1, 0.05), f(3, 2, 1)], threshold=1e-4) == [3, 1, 3]


def test_price_counts_each_candidates_sweeps_to_builtins_accuracy_at_the_cap():
    capped = dataclasses.replace(SHORT, solver=dataclasses.replace(SHORT.solver, velocity_iterations=20))
    priced = run_simulation(capped, 901, make_provider("price:jitter@0.01"))
    trials, reach = np.array(priced["trials"]), np.array(priced["reach"])  # (steps, 2) each: builtin, jitter
    at_cap = trials[:, 0] == 20
    assert at_cap.any() and (~at_cap).any()
    assert (reach[~at_cap] == trials[~at_cap]).all()  # where Builtin converges, the iterations themselves
    assert (reach[at_cap] <= 20).all() and (reach[at_cap, 1] < 20).any()  # under the cap: a start that nears


def test_mean_serves_the_candidates_mean_and_prices_it_beside_each_of_them():
    provider = make_provider("mean:jitter@0.1+jitter@0.1")
    assert provider.labels == ["builtin", "jitter@0.1", "jitter@0.1", "mean"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    assert [t[3] for t in served["trials"]] == its
    assert any(t[3] not in (t[1], t[2]) for t in served["trials"])  # the mean is neither candidate


def test_a_shadow_whose_server_is_away_serves_builtin_and_counts_the_fallbacks():
    shadowed = run_simulation(SHORT, 901, make_provider("shadow:server:zero"), client=None)
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    assert shadowed["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    assert shadowed["summary"]["fallback_steps"] == builtin["summary"]["steps_with_contacts"] > 0


def test_pick_never_does_worse_than_builtin_and_jitter_alone_wins_some_steps():
    # Candidates that know nothing: the per-step choice still finds cheaper starts
    # (docs/results.md, "Nor does choosing per step").
    picked = run_simulation(SHORT, 901, make_provider("pick:jitter@0.01+jitter@0.01"))
    its = [i for i, n in zip(picked["per_step"]["velocity_iterations"], picked["per_step"]["contact_points"]) if n]
    assert its == [min(t) for t in picked["trials"]]
    assert any(t[1] != t[2] for t in picked["trials"])  # the two jitters draw different noise
    assert np.mean(its) < mean_iterations("builtin")


def test_split_serves_its_warm_start_and_prices_the_two_parts_of_its_correction():
    provider = make_provider("split:oracle:near")
    assert provider.labels == ["builtin", "oracle:near", "oracle:near body-space", "oracle:near self-stress"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    assert [t[1] for t in served["trials"]] == its  # serves the warm start itself
    assert all(t[1] <= 2 for t in served["trials"])
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("split:oracle:near+oracle:half")


def test_boost_serves_its_warm_start_and_prices_it_with_its_self_stress_scaled():
    provider = make_provider("boost:oracle:near")
    assert provider.labels == ["builtin", "oracle:near"] + [f"oracle:near self-stress x{k:g}" for k in (0.5, 1.5, 2, 3)]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    assert [t[1] for t in served["trials"]] == its  # serves the warm start itself
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("boost:oracle:near+oracle:half")


def test_shrink_steps_as_builtin_and_prices_a_warm_starts_error_scaled_and_split():
    # W = oracle:half misses half of each correction; against the exact answer its error
    # shrunk to a quarter takes fewer iterations than W itself, on Builtin's own states.
    provider = make_provider("shrink:oracle:half+oracle:near")
    assert provider.labels == ["builtin", "oracle:half", "oracle:near", "oracle:half error x0.75",
                               "oracle:half error x0.5", "oracle:half error x0.25",
                               "oracle:half error's body-space part x0.5", "oracle:half error's self-stress x0.5"]
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    served = run_simulation(SHORT, 901, provider)
    assert served["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    trials = np.array(served["trials"])
    assert trials.shape[1] == 8 and trials[:, 2].max() <= 2  # the reference is the step's answer
    assert trials[:, 5].sum() < trials[:, 1].sum()
    with pytest.raises(ValueError, match="its reference"):
        make_provider("shrink:oracle:half")


def test_gate_steps_as_builtin_and_prices_a_warm_start_gated_per_point_by_a_reference():
    # W = the answer itself: every gate takes all of W wherever W differs from Box2D's warm start.
    provider = make_provider("gate:oracle:near+oracle:near")
    assert provider.labels == ["builtin", "oracle:near", "oracle:near", "oracle:near or builtin, the nearer at each point",
                               "oracle:near gated at each point", "oracle:near gated at each point, normal and tangent apart"]
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    served = run_simulation(SHORT, 901, provider)
    assert served["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    trials = np.array(served["trials"])
    assert trials.shape[1] == 6 and trials[:, 1:].max() <= 2
    with pytest.raises(ValueError, match="its reference"):
        make_provider("gate:oracle:near")


def test_face_steps_as_builtin_and_prices_the_step_solved_on_each_candidates_active_set():
    # On the answer's own face the admitted solve is the answer's motion with its open points
    # held: a start within a few sweeps of the end. W = oracle:half, half of each correction:
    # its face is Box2D's at many points, and its labels cost sweeps.
    provider = make_provider("face:oracle:half+oracle:near")
    assert provider.labels == ["builtin", "oracle:half", "oracle:near", "solved on oracle:near's face"] + [
        f"solved on oracle:near's face, {k} of oracle:half's labels" for k in (1, 3, 10)] + [
        "solved on oracle:near's face, oracle:half's labels where either says open",
        "solved on oracle:near's face, oracle:half's labels where both press",
        "solved on oracle:half's face", "solved on builtin's face", "solved on oracle:half's face read as labels",
        "solved on builtin's face, repaired 1x", "solved on builtin's face, repaired 2x",
        "solved on oracle:half's face read as labels, repaired 1x",
        "solved on oracle:half's face read as labels, repaired 2x"]
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    served = run_simulation(SHORT, 901, provider)
    assert served["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    trials = np.array(served["trials"])
    assert trials.shape[1] == 16
    assert trials[:, 3].mean() < 0.5 * trials[:, 0].mean()  # the answer's face, admitted
    assert trials[:, 3].sum() <= trials[:, 6].sum()  # ten of W's labels where they differ
    json.dumps(served["notes"])  # bench iterations writes them
    notes = np.array(served["notes"])  # per step: points, then where W's face differs from E's and how, then Box2D's
    assert notes.shape == (len(trials), 13) and (notes[:, 1:] <= notes[:, :1]).all() and notes[:, 1].sum() > 0
    np.testing.assert_array_equal(notes[:, 1], notes[:, 2:7].sum(axis=1))  # every difference is of one kind
    np.testing.assert_array_equal(notes[:, 7], notes[:, 8:13].sum(axis=1))
    with pytest.raises(ValueError, match="its reference"):
        make_provider("face:oracle:near")


def test_solved_serves_the_step_solved_on_its_candidates_labels_closed_loop():
    # A perfect classifier: the solution itself, read with the thresholds of the solution's
    # own face (a classifier's labels are read at 0.5 N s and the cone's limit). The step
    # solved on those labels and admitted is within a few sweeps of the end, on its own
    # trajectory, every step.
    provider = make_provider("solved:oracle:near")
    assert provider.labels == ["builtin", "oracle:near", "solved on oracle:near's face read as labels"]
    provider.FACE_LABELS = (1e-6, 0.99)
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 2].tolist() == its  # serves the solved start
    assert trials[:, 2].sum() < 0.5 * trials[:, 0].sum()
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    assert served["summary"]["mean_velocity_iterations"] < 0.5 * builtin["summary"]["mean_velocity_iterations"]
    # solved-forms: the same served starts, its other forms priced beside them
    forms = make_provider("solved-forms:oracle:near")
    assert forms.labels[3:] == ["solved on oracle:near's face read as labels, Box2D's self-stress",
                                "solved on oracle:near's face read as labels, admitted in 50 rounds",
                                "solved on oracle:near's face read as labels pressing above 0.25 N s",
                                "solved on oracle:near's face read as labels pressing above 0.75 N s"]
    forms.FACE_LABELS = provider.FACE_LABELS
    priced = np.array(run_simulation(SHORT, 901, forms)["trials"])
    np.testing.assert_array_equal(priced[:, :3], trials)
    assert priced.shape[1] == 7 and priced.min() >= 1
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("solved:oracle:near+oracle:half")
    # solved@P:W reads W's labels pressing above P N s
    assert make_provider("solved@0.75:oracle:near").FACE_LABELS == (0.75, 1.0)
    assert make_provider("solved@0.75:oracle:near").name == "solved@0.75:oracle:near"
    assert Pick.names_one("solved@0.75:oracle:near") and Pick.names_one("face:server:a+oracle:near")
    assert not Pick.names_one("server:default") and not Pick.names_one("oracle:near") and not Pick.names_one("builtin")
    for bad in ("solved@x:oracle:near", "solved@-1:oracle:near"):
        with pytest.raises(ValueError, match="pressing threshold"):
            make_provider(bad)


def test_a_gate_moves_builtin_toward_the_warm_start_only_where_that_nears_the_reference():
    b = (np.array([1.0, 1.0, 0.0]), np.array([0.0, 0.0, 0.0]))  # Box2D's warm start, N s
    w = (np.array([2.0, 2.0, 1.0]), np.array([0.0, 1.0, 0.0]))  # the model's
    e = (np.array([1.5, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))  # the answer
    nearer, share, apart = (np.column_stack(x) for x in Pick._gated(None, None, [b, w, e]))
    np.testing.assert_allclose(nearer, [[1, 0], [1, 0], [1, 0]])  # at the first point both lie 0.5 away: builtin
    np.testing.assert_allclose(share, [[1.5, 0], [1, 0], [1, 0]])
    np.testing.assert_allclose(apart, [[1.5, 0], [1, 1], [1, 0]])  # the second point's tangent alone moves


def test_admit_serves_its_warm_start_and_prices_its_admissible_forms():
    # Served here: the solution's body-space part alone (oracle:near-body-space). Brought
    # inside the friction cones by the smallest self-stress, the same motion takes far
    # fewer iterations: given the motion, the limits choose the self-stress.
    provider = make_provider("admit:oracle:near-body-space")
    assert provider.labels == ["builtin", "oracle:near-body-space", "oracle:near-body-space admissible",
                               "oracle:near-body-space body-space admissible",
                               "oracle:near-body-space body-space admissible, separating open",
                               "oracle:near-body-space moving bodies' motion admissible",
                               "oracle:near-body-space moving bodies' motion"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 1].tolist() == its  # serves the warm start itself
    assert trials[:, 2].sum() < 0.8 * trials[:, 1].sum()  # the same motion inside the cones
    assert trials[:, 3].sum() < 0.8 * trials[:, 1].sum()  # W's motion from Box2D's warm start: W itself, near enough
    assert trials.shape[1] == 7 and trials.min() >= 1  # and with the contacts its motion pulls apart; its moving bodies
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("admit:oracle:near+oracle:half")


def test_motion_serves_its_warm_start_and_prices_its_motion_scaled_and_admitted():
    # Served: the solution's motion alone (oracle:near-body-space). Its motion admitted at its own
    # size is the exact motion admitted, far fewer iterations than the motion served bare; too
    # large, it is another start.
    provider = make_provider("motion:oracle:near-body-space")
    w = "oracle:near-body-space"
    assert provider.labels == ["builtin", w, *(f"{w} motion x{k} admissible" for k in ("1", "1.25", "1.5")),
                               *(f"{w} moving bodies' motion x{k} admissible" for k in ("1", "1.25", "1.5"))]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 1].tolist() == its  # serves the warm start itself
    assert trials.shape[1] == 8 and trials.min() >= 1
    assert trials[:, 2].sum() < 0.8 * trials[:, 1].sum()
    assert trials[:, 3].tolist() != trials[:, 2].tolist()
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("motion:oracle:near+oracle:half")


def test_graft_serves_the_first_and_prices_it_with_the_seconds_moving_bodies_motion():
    # The base has the solution's motion at the resting bodies only (oracle:near-admissible-settled),
    # the donor at every body (oracle:near-body-space). The donor's moving bodies' motion grafted
    # onto the base and admitted puts every body's motion right: far fewer iterations than the base.
    provider = make_provider("graft:oracle:near-admissible-settled+oracle:near-body-space")
    assert provider.labels == ["builtin", "oracle:near-admissible-settled", "oracle:near-body-space",
                               "oracle:near-admissible-settled with oracle:near-body-space's moving bodies' motion admissible",
                               "oracle:near-admissible-settled with oracle:near-body-space's moving bodies' motion"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 1].tolist() == its  # serves the first warm start itself
    assert trials[:, 3].sum() < 0.8 * trials[:, 1].sum()
    with pytest.raises(ValueError, match="two warm starts"):
        make_provider("graft:oracle:near")


class _Biased(Provider):
    """The step's solution from Box2D's warm start (oracle:near) with BIAS N s more normal
    impulse at every point: a model that errs the same way at every step."""

    name = "biased"
    BIAS = 0.2

    def __init__(self):
        self._solution = OracleMix("near")

    def warm_start(self, engine, bodies, points, step):
        warm = self._solution.warm_start(engine, bodies, points, step)
        if warm is None:
            return None
        warm = np.stack(warm, axis=1).astype(np.float64)
        warm[:, 0] += self.BIAS
        return as_warm_start(warm)


def test_feedback_serves_its_warm_start_and_takes_off_an_error_that_repeats():
    provider = Pick([_Biased()], mode="feedback")
    assert provider.labels == ["builtin", "biased"] + [f"biased less {g:g} x its last error" for g in (0.25, 0.5, 1)]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 1].tolist() == its  # serves the warm start itself
    assert trials[0, 1] == trials[0, 2] == trials[0, 4]  # no previous step: nothing to take off
    # The more of last step's error taken off, the fewer iterations: the bias is what it was.
    assert trials[:, 4].mean() < trials[:, 3].mean() < trials[:, 2].mean() < trials[:, 1].mean()
    assert trials[:, 4].mean() < 0.6 * trials[:, 1].mean()
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("feedback:oracle:near+oracle:half")


def test_pick_keeps_the_cheapest_of_builtin_and_the_servers_answers_each_step(tmp_path):
    from server.process import ServerProcess
    from simclient.client import WarmStartClient

    spec = dataclasses.replace(SceneSpec.thesis(), steps=80)
    with ServerProcess(tmp_path) as server, WarmStartClient(server.address) as client:  # the server's providers only
        picked = run_simulation(spec, 904, make_provider("pick:server:zero+server:bad"), client=client, deadline_ms=1000)
    its = [i for i, n in zip(picked["per_step"]["velocity_iterations"], picked["per_step"]["contact_points"]) if n]
    trials = picked["trials"]  # per step with contacts: builtin's, zero's and bad's iterations
    assert len(trials) == len(its) > 0 and all(len(t) == 3 for t in trials)
    assert its == [min(t) for t in trials]
    assert any(t[1] < t[0] for t in trials)  # even zeros win some steps ...
    assert sum(t[2] for t in trials) > sum(t[0] for t in trials)  # ... and (50, 50) loses overall


def test_jittered_serves_its_warm_start_with_noise_far_below_the_tolerance_another_draw():
    plain = run_simulation(SHORT, 901, make_provider("shadow:copy"))
    drawn = run_simulation(SHORT, 901, make_provider("jittered@1e-7:copy"))
    assert make_provider("jittered:copy").name == "jittered:copy" and Pick.NOISE == 1e-7
    assert make_provider("jittered@1e-7:copy").labels == ["builtin", "copy", "copy plus noise of 1e-07 N s"]
    # Every step is priced from the served trajectory: builtin, the warm start, and the served noisy start.
    assert all(len(t) == 3 for t in drawn["trials"]) and len(drawn["trials"]) > 0
    # The noise is a hundred times below the tolerance: the same iterations step by step while the
    # trajectories agree, and the same noise on every run (seeded, a fresh provider per world).
    assert drawn["trials"][0][1:] == plain["trials"][0][1:] + [plain["trials"][0][1]]
    assert run_simulation(SHORT, 901, make_provider("jittered@1e-7:copy"))["trials"] == drawn["trials"]
    for bad in ("jittered@:copy", "jittered@big:copy", "jittered@0:copy", "jittered@-1e-7:copy",
                "jittered:copy+copy2"):
        with pytest.raises(ValueError):
            make_provider(bad)
