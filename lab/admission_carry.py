"""`deepcontact lab admission-carry`: where should a step's admission begin along a stream?

    deepcontact lab admission-carry --seeds 850-852

The admission's rounds are cut at the card's `rounds`, far from converged (deepcontact/
admission_kernels.h). Along a stream the same points come back step after step, and so could
the rounds' state: each point's iterate z and scaled dual s where its rounds stopped on the step
before (deepcontact.admission.AdmissionCarry, the face card's `carry`). This prices, on Box2D's
own trajectory of the thesis world (the same states for every answer), the default card's route
(deepcontact.faces.route_compiled; Box2D's start where the compiled dual declines) begun cold,
begun at the carried z with s = 0 (what `carry` does), begun at the carried z and s (dual), and
cold in ten times the rounds; and how far each answer lies from the route run to convergence
(2,000 rounds), a share of that answer's norm. Prints each answer's sweeps over Box2D's, over
the cold route's, and the median distance.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from bench.stats import ratio_interval

#: The answers priced: a name, carried (None: cold; else whether the dual is), the rounds over the card's.
STARTS = (("cold", None, 1), ("carried z", False, 1), ("carried z and s", True, 1), ("cold, 10x the rounds", None, 10))
#: Rounds of the route run to convergence, the distances' reference.
CONVERGED_ROUNDS = 2000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lab.face_card import add_arguments as face_card_arguments

    face_card_arguments(parser, "850-852")


def price(seed: int, steps: int, predictor) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """({"builtin" and each of STARTS: (steps,) sweeps}, {each of STARTS: (steps,) distance to the
    converged route, a share of its norm}) over the thesis world's steps with contacts."""
    from deepcontact.admission import AdmissionCarry
    from deepcontact.faces import route_compiled
    from lab.face_card import builtin_states

    face = predictor.settings
    carries = {name: AdmissionCarry(dual=bool(dual)) for name, dual, _ in STARTS if dual is not None}
    sweeps = {name: [] for name in ("builtin", *(s[0] for s in STARTS))}
    apart = {name: [] for name, _, _ in STARTS}

    def route(state, rounds, carry=None):
        return route_compiled(state.bodies, state.points, state.labels, state.friction, state.world.physics,
                              face["pressing"], face["share"], face["label_friction"], rounds, None, None,
                              face["relax"], face["rho"], carry)

    for k, state in builtin_states(seed, steps, predictor):
        converged = route(state, CONVERGED_ROUNDS)
        sweeps["builtin"].append(state.engine.trial(*state.builtin))
        for name, dual, times in STARTS:
            carry = carries[name].begin(state.points, k) if dual is not None else None
            answer = route(state, times * face["rounds"], carry)
            if carry is not None:
                carries[name].keep(state.points, k, carry) if answer is not None else carries[name].forget()
            if answer is None or converged is None:
                z, gap = np.stack(state.builtin, 1), np.nan
            else:
                z = answer.impulses
                gap = np.linalg.norm(z - converged.impulses) / max(np.linalg.norm(converged.impulses), 1e-12)
            sweeps[name].append(state.trial(z))
            apart[name].append(gap)
    return ({name: np.array(v, float) for name, v in sweeps.items()},
            {name: np.array(v, float) for name, v in apart.items()})


def run(args: argparse.Namespace) -> int:
    from lab.face_card import priced

    done = priced(args, "deepcontact lab admission-carry", price)
    if done is None:
        return 2
    predictor, runs = done
    print(f"the thesis world, seeds {args.seeds}, {args.model}'s route ({predictor.settings['rounds']} rounds) on "
          f"Box2D's states, {sum(len(r[0]['builtin']) for r in runs)} steps with contacts")
    print("| the admission begun | / builtin | / cold | distance to converged, median |\n|---|---|---|---|")
    for name, _, _ in STARTS:
        over_builtin = ratio_interval([r[0][name] for r in runs], [r[0]["builtin"] for r in runs]).text()
        over_cold = ratio_interval([r[0][name] for r in runs], [r[0]["cold"] for r in runs]).text()
        distance = np.nanmedian(np.concatenate([r[1][name] for r in runs]))
        print(f"| {name} | {over_builtin} | {over_cold} | {distance:.4f} |")
    return 0
