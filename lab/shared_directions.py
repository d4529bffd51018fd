"""The free directions several bodies share on a step of a zoo pyramid, seen densely, and the
compiled route's solve on them against the dual's
(docs/research/2026-12-07-free-directions-several-bodies-share.md):

    python -m lab.shared_directions --seed 901 --steps 30 90 120

For each step count: Box2D's own trajectory of `simclient.zoo.pyramid(seed)` run that many steps,
the step's points labelled by the oracle's solution (deepcontact.faces.contact_face), and

    points, sliding     the step's points and those that slide at its solution
    rank                the rank of L = A W^1/2 (singular values above 1e-7 of the largest) over its
                        body rows (3 D), the rows L leaves zero, and its least singular value in
                        that rank over the largest (the next are rounding's, 1e-15 and below)
    own, shared         K's free directions a body's own pushes account for (bodies one or two
                        unknowns push) and the rest, several bodies' (K' = K + c N N^T's null
                        directions off the zero rows), both from a dense eigendecomposition
    cond RQ             R Q's condition number, Q a basis of L's rows (the product
                        R Q (Q^T G Q)^-1 (Q^T K Q)^-1 Q^T L^T is S's pseudo-inverse where it is finite)
    product             that product's answer against numpy's pseudo-inverse (largest difference
                        over the largest entry), for a right-hand side drawn from the seed
    in bodies           whether the compiled route answered in the bodies' space
                        (deepcontact.faces.route_compiled), and its answer against the dual's
    bodies ms, dual ms  the route's solve, median of --calls calls, in the bodies' space where it
                        answers and with slide_in_bodies False (the dual at once)

Dense: each step costs a second or two of LAPACK at 600 points.
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np


def step_of(seed: int, steps: int):
    """(bodies, points, labels (P, 2), friction (P,), Physics) of the zoo pyramid `seed` after
    `steps` of Box2D's own steps, labelled by the oracle's solution."""
    from deepcontact.faces import contact_face, face_labels
    from deepcontact.kinematics import Physics
    from simclient import zoo
    from simclient.engine import Engine, SolverConfig

    world, dt = zoo.pyramid(seed)
    engine = Engine(world, SolverConfig(dt=dt))
    for _ in range(steps):
        engine.step()
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    exact = engine.oracle(threshold=1e-9, max_iterations=100000).astype(np.float64)
    mu = points["friction"].astype(np.float64)
    face = contact_face(exact, mu, pressing=1e-6, share=0.99)
    labels = face_labels(face)
    gravity = world.gravity
    return bodies, points, labels, mu, Physics(dt, (gravity[0], gravity[1]))


def dense_factors(bodies, points, labels, mu):
    """(L, R) (m, 3 D) of the face the labels read (pressing 0.5, share 1.0, as the route does):
    L = A W^1/2 its rows, R = C W^1/2 its columns, over the dynamic bodies' rows."""
    from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, contact_face
    from deepcontact.kinematics import contact_frame

    frame = contact_frame(bodies, points)
    face = contact_face(labels, mu, pressing=0.5, share=1.0)
    dynamic = np.flatnonzero(frame.dynamic)
    column = -np.ones(len(bodies), int)
    column[dynamic] = np.arange(len(dynamic))
    n_points, rows = len(points), 3 * len(dynamic)
    jacobian = np.zeros((2 * n_points, rows))
    for k, direction in ((0, frame.n), (1, frame.t)):
        for body, arm, sign in ((frame.a, frame.ra, -1.0), (frame.b, frame.rb, 1.0)):
            moving = column[body] >= 0
            at = 2 * np.flatnonzero(moving) + k
            first = 3 * column[body[moving]]
            v, r = direction[moving], arm[moving]
            np.add.at(jacobian, (at, first), sign * v[:, 0])
            np.add.at(jacobian, (at, first + 1), sign * v[:, 1])
            np.add.at(jacobian, (at, first + 2), sign * (r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0]))
    weight = np.stack([frame.inv_mass[dynamic], frame.inv_mass[dynamic], frame.inv_inertia[dynamic]], 1).ravel() ** 0.5
    pressing, sticking = np.flatnonzero(face != OPEN), np.flatnonzero(face == STICKS)
    slide = np.where(face == SLIDES_PLUS, 1.0, np.where(face == SLIDES_MINUS, -1.0, 0.0)) * mu
    a = np.vstack([jacobian[2 * pressing], jacobian[2 * sticking + 1]])
    c = a.copy()
    c[:len(pressing)] += slide[pressing, None] * jacobian[2 * pressing + 1]
    return a * weight, c * weight


def own_directions(lower: np.ndarray) -> np.ndarray:
    """(3 D, k) the free directions of bodies that one or two unknowns push, each in its body's
    three rows (what face_body_free_directions finds)."""
    found = []
    for body in range(lower.shape[1] // 3):
        block = lower[:, 3 * body:3 * body + 3]
        pushes = np.flatnonzero(np.abs(block).sum(1) > 0)
        if 0 < len(pushes) < 3:
            _, values, vt = np.linalg.svd(block[pushes])
            for v in vt[(values > 1e-12 * values[0]).sum():]:
                e = np.zeros(lower.shape[1])
                e[3 * body:3 * body + 3] = v
                found.append(e)
    return np.array(found).T if found else np.zeros((lower.shape[1], 0))


def report(seed: int, steps: int, calls: int) -> dict:
    from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, contact_face, route_compiled, solved_on_labels

    bodies, points, labels, mu, physics = step_of(seed, steps)
    face = contact_face(labels, mu, pressing=0.5, share=1.0)
    lower, right = dense_factors(bodies, points, labels, mu)
    system = lower @ right.T
    _, values, vt = np.linalg.svd(lower)
    rank = int((values > 1e-7 * values[0]).sum())
    zero = np.abs(lower).sum(0) == 0
    gram_k = lower.T @ lower
    own = own_directions(lower)
    k_prime = gram_k + np.trace(gram_k) / len(gram_k) * own @ own.T
    eigenvalues, vectors = np.linalg.eigh(k_prime)
    null = vectors[:, eigenvalues < 1e-12 * np.trace(k_prime) / len(k_prime)]
    null = null - np.eye(len(zero))[:, zero] @ null[zero]
    u, s, _ = np.linalg.svd(null, full_matrices=False)
    shared = int((s > 1e-6).sum())
    basis = vt[:rank].T
    rq = right @ basis
    rhs = np.random.default_rng(seed).normal(size=len(system))
    product = rq @ np.linalg.solve(basis.T @ right.T @ right @ basis,
                                   np.linalg.solve(basis.T @ gram_k @ basis, basis.T @ lower.T @ rhs))
    pinv = np.linalg.pinv(system, rcond=1e-12) @ rhs
    settings = dict(physics=physics, pressing=0.5, share=1.0, rounds=0)
    dual, _ = solved_on_labels(bodies, points, labels, mu, solver="dual", **settings)
    timed = {}
    for in_bodies in (True, False):
        runs = [route_compiled(bodies, points, labels, mu, slide_in_bodies=in_bodies, **settings) for _ in range(calls)]
        timed[in_bodies] = (runs[-1], 1e3 * statistics.median(r.solve_seconds for r in runs))
    compiled = timed[True][0]
    return {
        "steps": steps, "points": len(points), "sliding": int(np.isin(face, (SLIDES_PLUS, SLIDES_MINUS)).sum()),
        "pressing": int((face != OPEN).sum()), "rank": rank, "body_rows": lower.shape[1], "zero_rows": int(zero.sum()),
        "least": float(values[rank - 1] / values[0]),
        "own": own.shape[1], "shared": shared, "cond_rq": float(np.linalg.cond(rq)),
        "product": float(np.abs(product - pinv).max() / np.abs(pinv).max()),
        "in_bodies": bool(compiled.in_bodies),
        "against_dual": float(np.abs(compiled.impulses - dual).max() / max(1.0, np.abs(dual).max())),
        "bodies_ms": timed[True][1], "dual_ms": timed[False][1],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.shared_directions", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=901, help="the zoo pyramid's seed (default 901)")
    parser.add_argument("--steps", type=int, nargs="+", default=[30, 90], help="Box2D's steps before each (default 30 90)")
    parser.add_argument("--calls", type=int, default=15, help="route_compiled calls timed a way (default 15)")
    args = parser.parse_args(argv)
    if args.seed >= 10000 or any(s < 1 for s in args.steps) or args.calls < 1:
        parser.error("--seed below 10000, --steps and --calls at least 1")
    print("| steps | points (sliding) | rank of L / body rows (zero rows; its least singular value) | own, shared "
          "| cond R Q | product vs pinv | in bodies (vs the dual) | bodies ms | dual ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    for steps in args.steps:
        r = report(args.seed, steps, args.calls)
        print(f"| {r['steps']} | {r['points']} ({r['sliding']}) | {r['rank']} / {r['body_rows']} ({r['zero_rows']}; "
              f"{r['least']:.1e}) | {r['own']}, {r['shared']} | {r['cond_rq']:.0f} | {r['product']:.1e} | "
              f"{'yes' if r['in_bodies'] else 'no'} ({r['against_dual']:.1e}) | {r['bodies_ms']:.2f} | {r['dual_ms']:.2f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
