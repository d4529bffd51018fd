"""`deepcontact lab corrections`: how a served model's corrections compare with the solver's, by size.

    deepcontact lab corrections --model graph-mse --data data/thesis-val-801-820.h5

Replays recorded steps (`deepcontact generate`) through a model as the server
serves it (its card's combine and threshold included) and compares the served
correction (warm start minus Box2D's) with the solver's own correction (final
impulse minus Box2D's warm start), normal components, N s. Points are grouped
by the size of the solver's correction: the oracle experiments say the value
of a warm start lies at persisting points whose correction is small (docs/results.md,
"Where the iterations are"), and a plain MSE is ruled by the few large ones.

Per group: points; RMS of the solver's correction (Builtin's error); RMS error
of the served warm start; the share of points where a correction is served
(non-zero); and, among those, the share whose sign agrees with the solver's
(0.5 is a coin toss) and the share within half the solver's correction of it
(what the oracles say a warm start needs to pay). Pooled over the points: the
share of the solver's squared correction explained, the least-squares scale of
the served correction on the solver's (below 1: a shrunk answer) and their
correlation (`fit_of`).

`--reference oracle` compares with the step solved from zero to convergence
instead (files from `generate --oracle`): the recorded solve stops at 1e-4 N s
or 1000 sweeps and misses a 0.1-0.3 N s correction by about half its size.

`--model recorded` serves the impulses the recorded solve ended at, the
target `train-graph` fits by default: with `--reference oracle` it measures how
far that target lies from the converged solution.

`--model A,B,...` serves the mean of the named models' warm starts: whether
models that err differently cancel each other's errors (an ensemble), before
anyone builds a server that runs several. With `--agree K`, that mean only where
the models agree (their spread below K times its size, as `python -m
training.ensemble --agree K` serves it), Box2D's warm start elsewhere.

`--where lost-contact` keeps only the points one of whose dynamic bodies lost a
contact point since the previous step (a key there that is gone here), and
`--where kept-contacts` the others: the load such a point carried moves to the
body's other points, and the model's inputs show the points of this step only.
Whether the corrections the model misses are there is what the split asks.
`--where settled` keeps the points whose dynamic bodies both move slower than
0.01 m/s (deepcontact.kinematics.points_at_rest: a pile at rest, where the velocities a model reads are near 0),
and `--where moving` the others.

`--part body-space` compares only the part of each correction (served and the
solver's, both directions) that moves the bodies, and `--part self-stress` only
the rest, which moves none (deepcontact.kinematics.body_space_part): the oracles
say the self-stress holds most of a warm start's value and the other part most
of its size (docs/results.md, "Load the bodies' motion does not fix").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_models_argument
from deepcontact.io import write_json_atomic
from deepcontact.kinematics import BODY_DYNAMIC, REST_SPEED, body_space_part, points_at_rest

#: The point subsets `--where` selects (module docstring).
WHERE = ("all", "lost-contact", "kept-contacts", "settled", "moving")
_WHERE_TEXT = {"lost-contact": "on a body that lost a contact point since the previous step",
               "kept-contacts": "on bodies that kept all their contact points",
               "settled": "on bodies at rest", "moving": "on a moving body"}

#: What `--part` keeps of each correction (module docstring).
PARTS = ("whole", "body-space", "self-stress")

#: Upper edges of the groups of the solver's correction size (N s); the last group is open.
BANDS = (0.01, 0.1, 0.3, 1.0)


def add_replay_arguments(parser: argparse.ArgumentParser, model_help: str) -> None:
    """The arguments of a command that replays recorded steps through a model: --models,
    --model (its help is `model_help`), --data, --max-steps."""
    add_models_argument(parser)
    parser.add_argument("--model", default="default", help=model_help)
    parser.add_argument("--data", type=Path, required=True, help="recorded steps (HDF5 from `deepcontact generate`)")
    parser.add_argument("--max-steps", type=int, default=500, metavar="N",
                        help="replay at most N steps with contacts, drawn at random (default %(default)s)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_replay_arguments(parser, "model to replay (default: default); A,B,... replays the mean of their warm starts; "
                                 "'recorded' serves the recorded solve's own end (compare with --reference oracle)")
    parser.add_argument("--reference", choices=("final", "oracle"), default="final",
                        help="the solver's correction: to the impulses the recorded solve ended at (final, default) "
                             "or to the step solved from zero to convergence (oracle; data from generate --oracle)")
    parser.add_argument("--agree", type=float, metavar="K",
                        help="with several models: serve their mean only where their standard deviation is below "
                             "K times its size (python -m training.ensemble --agree), Box2D's warm start elsewhere")
    parser.add_argument("--where", choices=WHERE, default="all",
                        help="only the points on a body that lost a contact point since the previous step "
                             f"(lost-contact) or the others (kept-contacts); only those whose bodies move slower "
                             f"than {REST_SPEED:g} m/s (settled) or the others (moving); or all (default)")
    parser.add_argument("--part", choices=PARTS, default="whole",
                        help="compare only the part of each correction that moves the bodies (body-space) or the "
                             "self-stress that moves none (self-stress), or the whole correction (default)")
    parser.add_argument("--json", metavar="FILE", help="write the table here as JSON")


class RecordedSolve:
    """`--model recorded`: serves the impulses the recorded solve ended at (the file's
    own final impulses), as a model would that fitted `train-graph`'s default target exactly."""

    def predict(self, bodies, points, world, step, previous, friction=None):
        from server.predictors import Prediction

        return Prediction(points["impulse"].astype(np.float32))


def served_on_step(predictor, step) -> np.ndarray:
    """(P, 2) float32 N s: what `predictor` (a server predictor or RecordedSolve) serves at a
    recorded step (training.grids.iter_steps's Step), in a world spanning the step's points,
    with each point's friction where the predictor needs it (a face card)."""
    from server.predictors import World

    c = step.contacts
    world = World(((0.0, 0.0), tuple(np.maximum(c["point"].max(axis=0) + 1.0, 1.0))), step.physics)
    extra = {"friction": step.friction} if "point_friction" in getattr(predictor, "requires", ()) else {}
    return np.asarray(predictor.predict(step.bodies, c, world, 0, step.previous, **extra).impulses, np.float32)


def band_table(served: np.ndarray, solver: np.ndarray, new: np.ndarray) -> list[dict]:
    """Rows of the comparison (module docstring).

    served, solver: (P,) corrections to Box2D's warm start, normal, N s; new: (P,) bool, new points."""
    edges = (0.0, *BANDS, np.inf)
    groups = [(f"persisting, |c| in ({lo:g}, {hi:g}]", ~new & (np.abs(solver) > lo) & (np.abs(solver) <= hi))
              for lo, hi in zip(edges[:-1], edges[1:])]
    groups[0] = ("persisting, |c| <= 0.01", ~new & (np.abs(solver) <= BANDS[0]))
    groups += [("persisting, all", ~new), ("new points", new)]
    rows = []
    for name, m in groups:
        given = m & (served != 0)
        rows.append({
            "group": name, "points": int(m.sum()),
            "rms_correction": _rms(solver[m]), "rms_error": _rms(served[m] - solver[m]),
            "served_share": float(given.sum() / max(m.sum(), 1)),
            "sign_agreement": float(np.mean(np.sign(served[given]) == np.sign(solver[given]))) if given.any() else None,
            "within_half": (float(np.mean(np.abs(served[given] - solver[given]) <= 0.5 * np.abs(solver[given])))
                            if given.any() else None),
        })
    return rows


def lost_contact(step) -> np.ndarray:
    """(P,) bool: this step's points one of whose dynamic bodies had a point on the
    previous step whose key this step lacks (all False without a previous step).

    step: a deepcontact.channels.Step with bodies, contacts and previous."""
    c, p = step.contacts, step.previous
    if p is None or not len(p) or not len(c):
        return np.zeros(len(c), bool)
    gone = p[~np.isin(p["key"], c["key"])]
    lost = np.zeros(len(step.bodies), bool)
    lost[gone["body_a"]] = lost[gone["body_b"]] = True
    lost &= step.bodies["type"] == BODY_DYNAMIC
    return lost[c["body_a"]] | lost[c["body_b"]]


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x, dtype=np.float64)))) if len(x) else float("nan")


def _part(bodies: np.ndarray, points: np.ndarray, correction: np.ndarray, part: str) -> np.ndarray:
    """The `part` of (P, 2) corrections (N s), normal component: (P,)."""
    if part == "whole":
        return correction[:, 0]
    moves = body_space_part(bodies, points, correction)
    return (moves if part == "body-space" else correction - moves)[:, 0]


def fit_of(served: np.ndarray, solver: np.ndarray) -> dict[str, float]:
    """How the served corrections (P,) N s fit the solver's (P,) N s, pooled over points:
    `explained` (1 - error^2 / correction^2), `scale` (the least-squares s in
    served ~ s * solver: below 1 a shrunk answer, as a squared-error fit of an uncertain
    target gives) and their `correlation` (nan where either is constant)."""
    served, solver = np.asarray(served, np.float64), np.asarray(solver, np.float64)
    size = max(float(np.sum(solver ** 2)), 1e-30)
    spread = float(np.sqrt(np.sum(served ** 2) * size))
    return {"explained": 1.0 - float(np.sum((served - solver) ** 2)) / size,
            "scale": float(np.sum(served * solver)) / size,
            "correlation": float(np.sum(served * solver)) / spread if spread > 0 else float("nan")}


def replay(predictors, path: Path, max_steps: int, reference: str = "final", agree: float | None = None,
           part: str = "whole") -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(served, solver, new, where): the served and the solver's normal correction and the new-point
    flag at every point of up to max_steps recorded steps, (P,) each, and per `--where` choice
    but "all" the (P,) mask of its points. With several
    predictors, what is served is the mean of their warm starts (where they agree, with
    `agree`). reference "oracle" takes the solver's correction from the file's converged
    solve (ValueError when it has none). part: "whole", or the part of both corrections
    that moves the bodies ("body-space") or the self-stress ("self-stress"); with a part,
    agree must be None (the agreement is a normal-only rule)."""
    from training.ensemble import agreed_mean
    from training.grids import iter_steps, open_dataset, select_steps

    with open_dataset(path) as ds:
        steps = ds.steps
    served, solver, new, lost, at_rest = [], [], [], [], []
    for _, step in iter_steps(path, steps, select_steps(steps, max_steps)):  # loop over steps, not points
        c = step.contacts
        builtin = c["builtin"].astype(np.float64)
        warm = np.stack([served_on_step(p, step) for p in predictors])  # (M, P, 2)
        if reference == "oracle" and step.oracle is None:
            raise ValueError(f"{path} has no oracle impulses: record it with `deepcontact generate --oracle`")
        solved = (step.oracle if reference == "oracle" else c["impulse"]).astype(np.float64)
        if part == "whole":
            served.append(agreed_mean(warm[..., 0] - builtin[:, 0], agree))
        else:
            served.append(_part(step.bodies, c, warm.mean(axis=0) - builtin, part))
        solver.append(_part(step.bodies, c, solved - builtin, part))
        new.append(~c["builtin"].any(axis=1))
        lost.append(lost_contact(step))
        at_rest.append(points_at_rest(step.bodies, c))
    lost, at_rest = np.concatenate(lost), np.concatenate(at_rest)
    where = {"lost-contact": lost, "kept-contacts": ~lost, "settled": at_rest, "moving": ~at_rest}
    return np.concatenate(served), np.concatenate(solver), np.concatenate(new), where


def run(args: argparse.Namespace) -> int:
    from deepcontact.modelcard import ModelCardError
    from server.predictors import GridMismatch, load_model
    from training.grids import GridDataError

    if args.max_steps < 1:
        print("deepcontact lab corrections: --max-steps must be >= 1", file=sys.stderr)
        return 2
    names = [n for n in args.model.split(",") if n]
    if not names:
        print("deepcontact lab corrections: --model names no model", file=sys.stderr)
        return 2
    if args.agree is not None and args.part != "whole":
        print("deepcontact lab corrections: --agree compares whole corrections; leave out --part", file=sys.stderr)
        return 2
    if args.agree is not None and (len(names) < 2 or not args.agree > 0):
        print("deepcontact lab corrections: --agree K needs K > 0 and at least two models (--model A,B)",
              file=sys.stderr)
        return 2
    try:
        predictors = [RecordedSolve() if name == "recorded" else load_model(args.models / f"{name}.json")
                      for name in names]
        served, solver, new, where = replay(predictors, args.data, args.max_steps, args.reference, args.agree,
                                            args.part)
    except (ModelCardError, GridDataError, GridMismatch, OSError, ValueError) as exc:
        print(f"deepcontact lab corrections: {exc}", file=sys.stderr)
        return 2
    total = len(served)
    if args.where != "all":
        keep = where[args.where]
        served, solver, new = served[keep], solver[keep], new[keep]
    rows = band_table(served, solver, new)
    label = args.model if len(names) == 1 else f"the mean of {', '.join(names)}"
    if args.agree is not None:
        label += f" where they agree (K {args.agree:g})"
    against = "the converged solve's" if args.reference == "oracle" else "the solver's"
    subset = "" if args.where == "all" else f", {len(served)} of them {_WHERE_TEXT[args.where]}"
    if args.part != "whole":
        label += f", {args.part} part of each correction"
    print(f"{label} on {args.data} ({total} points{subset}): the served correction against {against} "
          "(normal, N s)")
    print("| points | n | RMS solver's correction | RMS error served | served share | sign agrees | within half |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        sign, half = ("–" if r[k] is None else f"{r[k]:.2f}" for k in ("sign_agreement", "within_half"))
        print(f"| {r['group']} | {r['points']} | {r['rms_correction']:.3g} | {r['rms_error']:.3g} | "
              f"{r['served_share']:.2f} | {sign} | {half} |")
    fit = fit_of(served, solver)
    print(f"\nExplained: {fit['explained']:.3f} of the solver's squared correction (1 - error^2 / correction^2, "
          f"{_rms(solver):.3g} N s RMS over {len(solver)} points); served = {fit['scale']:.3f} x the solver's "
          f"+ the rest (least squares), correlation {fit['correlation']:.3f}")
    if args.json:
        write_json_atomic(args.json, {"model": args.model, "data": str(args.data), "reference": args.reference,
                                      "agree": args.agree, "where": args.where, "part": args.part, "points": total,
                                      **fit, "rows": rows})
    return 0
