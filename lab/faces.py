"""`deepcontact lab faces`: how right a served model's answer is as an active set.

    deepcontact lab faces --model default --data data/thesis-val-801-820.h5

A step's solution lies on a face of the contact problem's limits: each point lets go,
sticks, or slides one way or the other (deepcontact.kinematics.contact_face). Solved on its
answer's own face a step needs 0.185x of Builtin's iterations, and with 3 or 10 of the
default's labels in it 0.687x and 0.933x (`face:` in `lab iterations`; docs/results.md,
"The active set alone"): a face pays only if it is wrong at very few of a step's points.
This replays recorded steps (`deepcontact generate`) through a model as the server serves it,
reads its answer, Box2D's warm start and the recorded solve's end as faces, and counts
where they differ: per step (mean, median, and the share of steps with at most 3 and at most
10 wrong labels), per point, and by kind. Reading a regression's answer as a face takes two
thresholds (a point presses above `--pressing` N s; it slides at `--share` of its friction
limit or more); comma-separated lists sweep them, and each reading is a row.

`--solve-time N` also times, on up to N of the steps, what serving the face route would cost
(docs/results.md "The active set alone, closed loop"): the step solved on the model's labels
(first reading; deepcontact.kinematics.solve_on_face) and that solve admitted
(nearest_admissible, in full and cut at `--rounds`), each the median and p90 in ms.

Recorded steps carry no friction coefficients: `--friction` gives the one every point has
(the thesis world's 0.5 by default), so files of worlds with mixed friction are not read
right by this command.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from deepcontact.io import write_json_atomic
from deepcontact.faces import FACE_ERRORS, contact_face, face_errors

#: How many wrong labels a step may have in the per-step shares printed (docs/results.md:
#: 3 and 10 of the default's labels in the answer's face need 0.687x and 0.933x of Builtin).
WRONG_AT_MOST = (3, 10)

def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lab.corrections import add_replay_arguments

    add_replay_arguments(parser, "model to replay (default: default); 'recorded' serves the recorded solve's own end "
                                 "(no label wrong: a check of the reading)")
    parser.add_argument("--friction", type=float, default=0.5, metavar="MU",
                        help="every point's friction coefficient; recorded steps carry none (default: the thesis "
                             "world's %(default)s)")
    parser.add_argument("--pressing", default="1e-6", metavar="N_S[,...]",
                        help="a served point presses above this normal impulse, N s; a list sweeps it (default 1e-6)")
    parser.add_argument("--share", default="0.99", metavar="S[,...]",
                        help="a served point slides at this share of its friction limit or more (above 1 for "
                             "labels written as impulses, train-graph --targets face); a list sweeps it (default 0.99)")
    parser.add_argument("--solve-time", type=int, default=0, metavar="N",
                        help="also time the step solved on the model's labels (first reading) and admitted, on up "
                             "to N steps: what serving it would cost (default 0: not timed)")
    parser.add_argument("--rounds", type=int, default=50, metavar="K",
                        help="with --solve-time: also time the admission cut at K rounds (default %(default)s)")
    parser.add_argument("--json", metavar="FILE", help="write the rows here as JSON")


def face_row(who: str, wrong: np.ndarray, points: np.ndarray, **reading) -> dict:
    """One reading's summary: wrong (S, 6) per step (wrong_labels), points (S,) per step."""
    per_step = wrong[:, 0]
    return {"who": who, **reading, "steps": len(per_step), "points": int(points.sum()),
            "right": 1.0 - float(per_step.sum()) / max(int(points.sum()), 1),
            "wrong_mean": float(per_step.mean()), "wrong_median": float(np.median(per_step)),
            **{f"steps_at_most_{k}": float((per_step <= k).mean()) for k in WRONG_AT_MOST},
            "kinds": dict(zip(FACE_ERRORS, wrong[:, 1:].mean(axis=0).tolist()))}


def replay(predictor, path: Path, max_steps: int):
    """Yields (served (P, 2), builtin (P, 2), recorded (P, 2)) float64 N s and the step
    (training.grids' record: bodies, contacts, physics) for up to max_steps recorded steps
    with contacts: the model's answer as served, Box2D's warm start and where the recorded
    solve ended."""
    from lab.corrections import served_on_step
    from training.grids import iter_steps, open_dataset, select_steps

    with open_dataset(path) as ds:
        steps = ds.steps
    for _, step in iter_steps(path, steps, select_steps(steps, max_steps)):  # a loop over steps, not points
        c = step.contacts
        served = served_on_step(predictor, step)
        yield (np.asarray(served, np.float64), c["builtin"].astype(np.float64), c["impulse"].astype(np.float64), step)


def _floats(text: str, name: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v]
    except ValueError:
        values = []
    if not values:
        raise ValueError(f"--{name} takes numbers separated by commas, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    from lab.corrections import RecordedSolve
    from deepcontact.modelcard import ModelCardError
    from server.predictors import GridMismatch, load_model
    from training.grids import GridDataError

    try:
        pressing, shares = _floats(args.pressing, "pressing"), _floats(args.share, "share")
        if args.max_steps < 1 or not args.friction > 0 or any(not s > 0 for s in shares) or min(pressing) < 0 \
                or args.solve_time < 0 or args.rounds < 1:
            raise ValueError("needs --max-steps >= 1, --friction > 0, --pressing >= 0, --share > 0, "
                             "--solve-time >= 0 and --rounds >= 1")
        predictor = RecordedSolve() if args.model == "recorded" else load_model(args.models / f"{args.model}.json")
        steps = list(replay(predictor, args.data, args.max_steps))
    except (ModelCardError, GridDataError, GridMismatch, OSError, ValueError) as exc:
        print(f"deepcontact lab faces: {exc}", file=sys.stderr)
        return 2
    if not steps:
        print(f"deepcontact lab faces: {args.data} has no steps with contacts", file=sys.stderr)
        return 2
    points = np.array([len(s[0]) for s in steps])
    mus = [np.full(n, args.friction) for n in points]
    truth = [contact_face(recorded, mu) for (_, _, recorded, _), mu in zip(steps, mus)]
    rows = [face_row("builtin", np.array([face_errors(contact_face(b, mu), t) for (_, b, _, _), mu, t
                                          in zip(steps, mus, truth)]), points)]
    for p in pressing:
        for s in shares:
            wrong = np.array([face_errors(contact_face(w, mu, pressing=p, share=s), t)
                              for (w, _, _, _), mu, t in zip(steps, mus, truth)])
            rows.append(face_row(args.model, wrong, points, pressing=p, share=s))
    print(f"{args.model} and Box2D's warm start on {args.data} ({len(steps)} steps, {points.sum()} points, "
          f"friction {args.friction:g}), read as faces against the recorded solve's end:")
    print("| read | points right | wrong labels a step, mean | median | steps with <= 3 | <= 10 | "
          + " | ".join(FACE_ERRORS) + " |")
    print("|---|---|---|---|---|---|" + "---|" * len(FACE_ERRORS))
    for r in rows:
        read = "builtin" if r["who"] == "builtin" else f"{r['who']}, pressing {r['pressing']:g}, share {r['share']:g}"
        print(f"| {read} | {r['right']:.3f} | {r['wrong_mean']:.1f} | {r['wrong_median']:.0f} | "
              f"{r['steps_at_most_3']:.2f} | {r['steps_at_most_10']:.2f} | "
              + " | ".join(f"{v:.1f}" for v in r["kinds"].values()) + " |")
    timed = solve_times(steps[:args.solve_time], mus, pressing[0], shares[0], args.rounds) if args.solve_time else None
    if timed:
        print(f"\nThe step solved on {args.model}'s labels (pressing {pressing[0]:g}, share {shares[0]:g}) and admitted, "
              f"on {timed['steps']} steps ({timed['points_median']:.0f} points a step, median), ms:")
        print("| stage | median | p90 |\n|---|---|---|")
        for stage, label in (("solve", "solve_on_face"), ("admit", "nearest_admissible, in full"),
                             ("admit_cut", f"nearest_admissible, {args.rounds} rounds")):
            print(f"| {label} | {timed[stage]['median']:.1f} | {timed[stage]['p90']:.1f} |")
    if args.json:
        write_json_atomic(args.json, {"model": args.model, "data": str(args.data), "friction": args.friction,
                                      "rows": rows, **({"solve_ms": timed} if timed else {})})
    return 0


def solve_times(steps: list, mus: list, pressing: float, share: float, rounds: int) -> dict:
    """Per-step wall time (ms, median and p90) of solve_on_face on the served answer read as
    labels, and of nearest_admissible in full and cut at `rounds` rounds; steps as replay yields."""
    import time

    from deepcontact.admission import nearest_admissible
    from deepcontact.faces import OPEN, solve_on_face
    from deepcontact.kinematics import contact_frame

    times = {"solve": [], "admit": [], "admit_cut": []}
    for (served, _, _, step), mu in zip(steps, mus):  # a loop over steps, each timed alone
        bodies, points = step.bodies, step.contacts
        face = contact_face(served, mu, pressing=pressing, share=share)
        t0 = time.perf_counter()
        frame = contact_frame(bodies, points)
        solved = solve_on_face(bodies, points, face, mu, step.physics, frame)
        t1 = time.perf_counter()
        nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, frame=frame)
        t2 = time.perf_counter()
        nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, frame=frame, iterations=rounds)
        t3 = time.perf_counter()
        for k, dt in (("solve", t1 - t0), ("admit", t2 - t1), ("admit_cut", t3 - t2)):
            times[k].append(1e3 * dt)
    return {"steps": len(steps), "points_median": float(np.median([len(s[0]) for s in steps])),
            **{k: {"median": float(np.median(v)), "p90": float(np.percentile(v, 90))} for k, v in times.items()}}
