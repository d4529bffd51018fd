"""`deepcontact transfer-table`: reproduce thesis Table 1 (§5.5).

How much does a round trip particle -> grid -> particle change a value, for
grid resolution and SPH support radius h in {0.125, 0.25, 0.5} m?  On settled
thesis worlds (seeds 900.. by default, simulated 200 steps of 0.01 s so the
bodies lie in a pile) it transfers

  (a) every dynamic body's mass onto a grid (P2G) and back (SPH G2P), and
  (b) every contact point's final normal impulse likewise,

and reports the average absolute difference per particle, pooled over all
worlds, next to the thesis's numbers, with how many particles were lost on
the way (no node within h of them) or fell outside the domain.  The 0.25 m /
0.5 m pair is the one the thesis (and this project) uses.

    deepcontact transfer-table [--worlds 25] [--steps 200] [--json FILE]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from deepcontact.io import write_json_atomic

VALUES = (0.125, 0.25, 0.5)  # m, for both the resolution and h

#: Thesis Table 1, (resolution, h) -> (avg body diff, avg contact diff).
THESIS_TABLE_1 = {
    (0.125, 0.125): (0.0000, 0.0000),
    (0.125, 0.25): (0.0000, 0.0000),
    (0.125, 0.5): (0.0000, 0.0191),
    (0.25, 0.125): (0.1137, 0.0480),
    (0.25, 0.25): (0.0000, 0.0000),
    (0.25, 0.5): (0.0000, 0.0195),
    (0.5, 0.125): (0.5177, 0.2349),
    (0.5, 0.25): (0.1074, 0.0589),
    (0.5, 0.5): (0.0000, 0.0237),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--worlds", type=int, default=25, help="number of thesis worlds (default 25, as in the thesis)")
    parser.add_argument("--steps", type=int, default=200, help="steps simulated before measuring (default 200)")
    parser.add_argument("--first-seed", type=int, default=900, help="seed of the first world; the others follow (default 900)")
    parser.add_argument("--kernel", default="poly6", choices=["poly6", "spiky", "gaussian"], help="SPH kernel (default poly6)")
    parser.add_argument("--json", metavar="FILE", help="write the table here as JSON")


def settled_particles(seed: int, steps: int):
    """One settled world's particles.

    Returns (body positions (B, 2) m, masses (B,) kg, contact points (P, 2)
    m, normal impulses (P,) N s).
    """
    from deepcontact.channels import Step, channel_values, particle_positions
    from simclient.scene import SceneSpec, settled_world

    engine = settled_world(SceneSpec.thesis(), seed, steps)
    engine.collide()
    engine.solve()  # fills the contact points' final impulses
    step = Step(engine.bodies(), engine.contacts())
    return (
        particle_positions("bodies", step),
        channel_values(["mass"], step)[:, 0],
        particle_positions("contacts", step),
        channel_values(["impulse_normal"], step)[:, 0],
    )


def round_trip(positions: np.ndarray, values: np.ndarray, spec) -> dict:
    """P2G then SPH G2P of one value per particle; differences and losses."""
    from deepcontact.transfer import g2p, p2g

    grid, there = p2g(positions, values, spec, outside="drop")
    back, home = g2p(grid, positions, spec, outside="drop")
    return {
        "abs_diff": np.abs(back[:, 0].astype(np.float64) - values),
        "lost_p2g": there.n_lost,
        "lost_g2p": home.n_lost,
        "outside": there.n_outside,
    }


def table(worlds: list, kernel: str = "poly6") -> list[dict]:
    """One row per (resolution, h): pooled average |difference| for bodies and contacts."""
    from deepcontact.gridspec import GridSpec
    from simclient.scene import SceneSpec

    lower, upper = SceneSpec.thesis().domain
    rows = []
    for res in VALUES:
        for h in VALUES:
            spec = GridSpec.for_domain(lower, upper, res, h, kernel=kernel)
            row: dict = {"resolution": res, "h": h, "grid": list(spec.shape)}
            for name, (pos, vals) in (("body", (0, 1)), ("contact", (2, 3))):
                trips = [round_trip(w[pos], w[vals], spec) for w in worlds]
                diffs = np.concatenate([t["abs_diff"] for t in trips])
                row[f"{name}_avg_diff"] = float(diffs.mean()) if len(diffs) else 0.0
                for key in ("lost_p2g", "lost_g2p", "outside"):
                    row[f"{name}_{key}"] = int(sum(t[key] for t in trips))
            row["thesis_body_avg_diff"], row["thesis_contact_avg_diff"] = THESIS_TABLE_1[(res, h)]
            rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    left = f"{'res':>5} {'h':>5}  {'Avg body diff':>13} {'thesis':>7} {'lost':>9}   "
    head = left + f"{'res':>5} {'h':>5}  {'Avg contact diff':>16} {'thesis':>7} {'lost':>9}"
    lines = [f"{'(a) body mass, kg':{len(left)}}(b) contact normal impulse, N s", head]
    for r in rows:
        lost_b = f"{r['body_lost_p2g']}/{r['body_lost_g2p']}"
        lost_c = f"{r['contact_lost_p2g']}/{r['contact_lost_g2p']}"
        lines.append(
            f"{r['resolution']:5.3f} {r['h']:5.3f}  {r['body_avg_diff']:13.4f} {r['thesis_body_avg_diff']:7.4f} {lost_b:>9}   "
            f"{r['resolution']:5.3f} {r['h']:5.3f}  {r['contact_avg_diff']:16.4f} {r['thesis_contact_avg_diff']:7.4f} {lost_c:>9}"
        )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.worlds < 1 or args.steps < 0:
        raise SystemExit("transfer-table: --worlds must be >= 1 and --steps >= 0")
    seeds = list(range(args.first_seed, args.first_seed + args.worlds))
    t0 = time.perf_counter()
    worlds = [settled_particles(seed, args.steps) for seed in seeds]
    simulated_s = time.perf_counter() - t0
    rows = table(worlds, args.kernel)
    n_bodies = sum(len(w[1]) for w in worlds)
    n_contacts = sum(len(w[3]) for w in worlds)

    print(
        f"Thesis Table 1: average |after P2G -> SPH G2P - before| per particle, {args.kernel} kernel\n"
        f"{args.worlds} thesis worlds (seeds {seeds[0]}-{seeds[-1]}) after {args.steps} steps: "
        f"{n_bodies} bodies (mass {worlds[0][1][0]:.4f} kg each), {n_contacts} contact points "
        f"(mean normal impulse {np.mean(np.concatenate([w[3] for w in worlds])):.4f} N s)\n"
        "lost = particles with no node within h, in P2G / in G2P (summed over the worlds)\n"
    )
    print(format_table(rows))
    outside = sum(r["body_outside"] + r["contact_outside"] for r in rows)
    if outside:
        print(f"\n{outside} particles fell outside the domain and were left out")
    if args.json:
        write_json_atomic(
            args.json,
            {
                "seeds": seeds,
                "steps": args.steps,
                "kernel": args.kernel,
                "bodies": n_bodies,
                "contact_points": n_contacts,
                "simulation_s": simulated_s,
                "rows": rows,
            },
        )
        print(f"\nwrote {args.json}")
    return 0
