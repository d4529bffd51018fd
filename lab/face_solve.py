"""`deepcontact lab face-solve`: what the face route's solve costs a step, by the step's size,
and how near its two ways of solving agree.

Records a thesis world on a benchmark seed (bench.server.record_steps), passes each step
through the wire as the server receives it, reads the face card's classifier on it in this
process, and times on every step with contacts:
  system   face_system, the linear system on the labels' unknowns (summed over the point pairs, in C)
  operator the same system the way the route built it before: the dense (2P, 2P)
           contact_operator, then its rows and columns on the face
  dual     minimum_norm_solve: S S^T, a Cholesky factorization, S^T y (a card's solver "dual")
  gelsy    the same least-squares problem by LAPACK's gelsy (solver "gelsy", the default)
  admit    nearest_admissible at the card's rounds (and whether the solve was admissible
           as it was, so that the admission had nothing to do)
  route    solved_on_labels, all of it, with the card's solver (the server's G2P stage of a face card)
  glibc    the same route at once again with glibc's malloc at its starting thresholds, not
           keeping freed memory as serve does (server/heap.py), and its extra over the route,
           the median of the step-by-step differences
and how far each solver's answer lies from the pseudo-inverse's with singular values below 1e-10
of the largest taken as zero (numpy's pinv; a face's system has none between about 1e-12 and
1e-6), |x - x_pinv| / |x_pinv|, and from each other. Medians by size, in ms; one process, one
thread of BLAS (as `deepcontact serve` runs).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_models_argument, add_seed_argument
from deepcontact.io import write_json_atomic

SIZES = ((1, 100), (100, 150), (150, 200), (200, 10**6))
#: The reference solution's cut: singular values below this share of the largest count as zero.
PINV_RCOND = 1e-10


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_models_argument(parser)
    parser.add_argument("--model", default="default", help="a face card (default: default)")
    add_seed_argument(parser, "thesis-world seed (default 903)", default=903)
    parser.add_argument("--steps", type=int, default=250, help="steps recorded (default 250)")
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before SciPy loads OpenBLAS, as serve does
    from server.heap import keep_freed_memory

    paired_heap = keep_freed_memory()  # as serve does (server/heap.py); False: not glibc
    import scipy.linalg

    from bench.server import record_steps
    from deepcontact import wire
    from deepcontact.admission import nearest_admissible, project_to_cones
    from deepcontact.faces import OPEN, contact_face, face_system, minimum_norm_solve, solve_on_face, solved_on_labels
    from deepcontact.kinematics import contact_frame, contact_operator, contact_velocities
    from deepcontact.modelcard import ModelCard, ModelCardError
    from server.predictors import World, load_model
    from simclient.scene import SceneSpec

    path = args.models / f"{args.model}.json"
    try:
        card = ModelCard.load(path)
        if card.face is None:
            print(f"deepcontact lab face-solve: {path} has no face: name a face card", file=sys.stderr)
            return 2
        # The classifier whose answer the route reads: the card's alias target, or the card itself.
        classifier = load_model(args.models / f"{ModelCard.alias_target(path) or args.model}.json")
    except (OSError, ModelCardError) as exc:
        print(f"deepcontact lab face-solve: {exc}", file=sys.stderr)
        return 2
    face_of = card.face
    thesis = SceneSpec.thesis()
    (lx, ly), (ux, uy) = thesis.domain
    world = World(((float(lx), float(ly)), (float(ux), float(uy))), thesis.physics)
    rows = []
    for k, (bodies, points, friction) in enumerate(record_steps(args.seed, args.steps)):
        if len(points) == 0:
            continue
        sent = wire.encode_step(k, args.model, bodies, points, builtin=points["builtin"], friction=friction)
        bodies, points = wire.decode_step(sent, max_bodies=10**4, max_points=10**6)
        mu = wire.decode_friction(sent).astype(np.float64)
        extra = {"friction": mu.astype(np.float32)} if "point_friction" in classifier.requires else {}
        labels = classifier.predict(bodies, points, world, k, **extra).impulses.astype(np.float64)
        face = contact_face(labels, mu, pressing=face_of["pressing"], share=face_of["share"])
        if not (face != OPEN).any():
            continue
        frame = contact_frame(bodies, points)
        t0 = time.perf_counter()
        system, eq, slide = face_system(frame, face, mu)
        t1 = time.perf_counter()
        operator = contact_operator(frame)
        pressing, sticking = eq[eq % 2 == 0], eq[eq % 2 == 1] - 1
        np.concatenate([operator[np.ix_(eq, pressing)] + operator[np.ix_(eq, pressing + 1)] * slide,
                        operator[np.ix_(eq, sticking + 1)]], axis=1)
        t1b = time.perf_counter()
        rhs = -contact_velocities(bodies, points, physics=world.physics).ravel()[eq]
        t2 = time.perf_counter()
        dual = minimum_norm_solve(system, rhs)
        t3 = time.perf_counter()
        gelsy = scipy.linalg.lstsq(system, rhs, lapack_driver="gelsy", check_finite=False)[0]
        t4 = time.perf_counter()
        pinv = np.linalg.pinv(system, rcond=PINV_RCOND) @ rhs
        size = max(float(np.linalg.norm(pinv)), 1e-300)
        solved = solve_on_face(bodies, points, face, mu, world.physics, frame)
        t5 = time.perf_counter()
        nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, iterations=face_of["rounds"],
                           frame=frame)
        t6a = time.perf_counter()
        route = (bodies, points, labels, mu, world.physics, face_of["pressing"], face_of["share"], face_of["rounds"],
                 face_of["label_friction"])
        route_kw = {"damping": face_of["damping"], "solver": face_of["solver"]}
        # The route as served; with glibc's malloc also at its starting thresholds, the two in turn
        # first on alternate steps (the second of two runs finds its inputs in cache).
        heaps = ((True, False) if k % 2 else (False, True)) if paired_heap else (True,)
        took = {}
        for kept in heaps:
            if paired_heap:
                keep_freed_memory(kept=kept)
            t6 = time.perf_counter()
            solved_on_labels(*route, **route_kw)
            took[kept] = 1e3 * (time.perf_counter() - t6)
        route_ms, glibc_ms = took[True], took.get(False)
        differs = None if dual is None else float(np.linalg.norm(dual - gelsy) / max(np.linalg.norm(gelsy), 1e-300))
        admissible = bool(np.array_equal(project_to_cones(solved, mu) * (face != OPEN)[:, None], solved))
        rows.append({"points": len(points), "unknowns": len(rhs), "system_ms": 1e3 * (t1 - t0),
                     "gelsy_from_pinv": float(np.linalg.norm(gelsy - pinv)) / size,
                     "dual_from_pinv": None if dual is None else float(np.linalg.norm(dual - pinv)) / size,
                     "operator_ms": 1e3 * (t1b - t1), "admissible": admissible,
                     "dual_ms": 1e3 * (t3 - t2), "gelsy_ms": 1e3 * (t4 - t3), "admit_ms": 1e3 * (t6a - t5),
                     "route_ms": route_ms, "route_glibc_heap_ms": glibc_ms, "differs": differs})
    if not rows:
        print(f"deepcontact lab face-solve: no step of seed {args.seed} has a pressing label", file=sys.stderr)
        return 2
    by_size = []
    print(f"{args.model} on thesis seed {args.seed}: {len(rows)} steps; medians in ms")
    print("| points | steps | unknowns | system | operator (before) | dual | gelsy | admission | solve admissible | "
          "whole route | the same, heap as glibc starts | its extra, paired |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for lo, hi in SIZES:
        these = [r for r in rows if lo <= r["points"] < hi]
        if not these:
            continue
        med = {key: float(np.median([r[key] for r in these])) for key in
               ("unknowns", "system_ms", "operator_ms", "dual_ms", "gelsy_ms", "admit_ms", "route_ms")}
        if paired_heap:
            med["route_glibc_heap_ms"] = float(np.median([r["route_glibc_heap_ms"] for r in these]))
            med["glibc_heap_extra_ms"] = float(np.median([r["route_glibc_heap_ms"] - r["route_ms"] for r in these]))
        heap = (f"{med['route_glibc_heap_ms']:.2f} | {med['glibc_heap_extra_ms']:+.2f}" if paired_heap
                else "– | –")
        admissible = sum(r["admissible"] for r in these)
        by_size.append({"points": [lo, hi], "steps": len(these), "admissible": admissible, **med})
        label = f"{lo}-{hi - 1}" if hi < 10**6 else f"{lo}+"
        print(f"| {label} | {len(these)} | {med['unknowns']:.0f} | {med['system_ms']:.2f} | {med['operator_ms']:.2f} | "
              f"{med['dual_ms']:.2f} | {med['gelsy_ms']:.2f} | {med['admit_ms']:.2f} | {admissible} | "
              f"{med['route_ms']:.2f} | {heap} |")
    differs = np.array([r["differs"] for r in rows if r["differs"] is not None])
    declined = sum(r["differs"] is None for r in rows)
    agreement = {"median": float(np.median(differs)) if len(differs) else None,
                 "share_above_1e-6": float(np.mean(differs > 1e-6)) if len(differs) else None,
                 "share_above_1e-3": float(np.mean(differs > 1e-3)) if len(differs) else None,
                 "declined_to_gelsy": declined}
    print(f"dual against gelsy, |x_dual - x_gelsy| / |x_gelsy|: median {agreement['median']:.1e}, above 1e-6 at "
          f"{100 * agreement['share_above_1e-6']:.0f} % of steps, above 1e-3 at {100 * agreement['share_above_1e-3']:.0f} %; "
          f"{declined} steps left to gelsy (an inconsistent system)")
    for solver in ("gelsy", "dual"):
        off = np.array([r[f"{solver}_from_pinv"] for r in rows if r[f"{solver}_from_pinv"] is not None])
        agreement[f"{solver}_from_pinv"] = {"median": float(np.median(off)), "above_1e-6": int(np.sum(off > 1e-6)),
                                            "above_1e-3": int(np.sum(off > 1e-3)), "steps": len(off)}
        print(f"{solver} against pinv (rcond {PINV_RCOND:g}): median {np.median(off):.1e}, above 1e-6 at "
              f"{np.sum(off > 1e-6)} and above 1e-3 at {np.sum(off > 1e-3)} of {len(off)} steps")
    if args.json:
        write_json_atomic(Path(args.json), {"model": args.model, "seed": args.seed, "steps": len(rows),
                                            "by_size": by_size, "agreement": agreement, "rows": rows})
    return 0
