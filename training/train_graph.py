"""`deepcontact train-graph`: fit the contact-graph model and export it with its card.

    deepcontact train-graph --train data/thesis-train-1-300.h5 --train data/family-train-1-300.h5 \\
        --val data/thesis-val-801-820.h5 --out models/graph.onnx

One command from recorded data to a served model: reads the contact graphs
of the files' steps (cached as .npz beside --cache), normalizes the point
channels with the training files' mean and std, trains with Adam on a cosine
schedule until the validation loss has not improved for --patience epochs,
and writes the best epoch's ONNX file and card (kind "graph"), both under a
temporary name first. The card's GridSpec carries the channels and their
normalization; a graph model ignores its geometry.

The model predicts the correction to Box2D's warm start at each point
(correction_normal, correction_tangent, N s; with --targets oracle the
correction to the step solved from zero to convergence, oracle_correction_*;
with --teacher CARD what another graph model answers there, training/teacher.py);
--combine says how the server serves it (residual: everywhere; new-points: at
new points only).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_seed_argument
from deepcontact.gridspec import GridSpec
from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCard
from training import dataset, machine
from deepcontact.channels import CHANNELS, mirror_signs
from training.contact_graph import (GRAPH_INPUTS, GRAPH_TARGETS, SCALED_GRAPH_INPUTS, MIRROR_GEOMETRY, GraphSet, build_graph_set,
                                    step_converged, step_iterations)
from training.grids import GridDataError
from training.second_pass import SecondPassError, moved
from training.second_pass import check as check_second_pass
from training.second_pass import check_inputs as check_second_pass_inputs
from training.second_pass import moves as second_pass_moves
from training.teacher import Teacher, taught

# What the correction is measured to: the solver's own end of the recorded step (Box2D's warm
# start, stopped at 1e-4 N s or 1000 sweeps), or the step solved from zero to 1e-6 N s
# (`generate --oracle`), which the stopped solve misses by about half of a 0.1-0.3 N s
# correction (docs/results.md, "Training on the converged solution").
TARGETS = {"final": GRAPH_TARGETS, "oracle": ("oracle_correction_normal", "oracle_correction_tangent"),
           "face": ("face_correction_normal", "face_correction_tangent"),
           "face-labels": ("face_normal", "face_tangent")}

CACHE_VERSION = 4  # GraphSet fields (3: speed; 4: face targets read at each point's friction)
RELATIVE_FLOOR = 0.05  # N s: the relative loss's floor, the noise a warm start can afford (docs/results.md)
#: relative-moving: each moving body's correction counts as at least this push (N s) in its step's
#: denominator: about an eighth of what gravity gives a thesis disc in a step (0.785 kg x 0.098 m/s).
MOVING_FLOOR = 0.01
#: mse-sticking: friction at this share of its bound or more counts as sliding (simclient.provider.CONE_SHARE).
STICKING_SHARE = 0.99
LOG_FLOOR = 1e-8  # (N s)^2: solver-log's floor, far below any residual the solver stops at
NORMS = (2, 4, 8)  # --norm: higher ones underflow float32 (and their floor with them)
ORDERS = ("jacobi", "gauss-seidel")
DEFAULTS = {"epochs": 40, "batch_size": 32, "lr": 2e-3, "patience": 6, "width": 32, "rounds": 3}


class TrainingDiverged(RuntimeError):
    """The loss stopped being a number; nothing is written."""


class WeightsMismatch(ValueError):
    """--init names the weights of another network."""


class ResumeMismatch(ValueError):
    """--resume names the state of a run with other arguments."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command's arguments, in groups that --help lists apart."""
    for title, add in (("data and outputs", _data_arguments), ("the network and what it serves", _network_arguments),
                       ("the loss", _loss_arguments), ("the schedule", _schedule_arguments)):
        add(parser.add_argument_group(title))


def _data_arguments(parser) -> None:
    """What to read, where to write, and how much of it."""
    parser.add_argument("--train", type=Path, action="append", required=True,
                        help="training data (HDF5 from `deepcontact generate`); repeat for several files")
    parser.add_argument("--val", type=Path, action="append", required=True, help="validation data; repeatable")
    parser.add_argument("--out", type=Path, required=True, help="ONNX file to write; the card goes beside it")
    parser.add_argument("--name", help="model name in the card (default: the --out file's stem)")
    parser.add_argument("--max-steps-per-file", type=int, metavar="N", help="use at most N steps of each file")
    parser.add_argument("--max-val-steps", type=int, metavar="N", help="use at most N steps of each validation file")
    parser.add_argument("--cache", type=Path, default=Path("runs/graph-cache"),
                        help="folder for the contact graphs read from the data files (default %(default)s)")
    parser.add_argument("--checkpoints", type=Path, metavar="DIR",
                        help="also write every epoch's network to DIR as NAME-eK.onnx with its card, a models "
                             "folder that `deepcontact bench iterations --models DIR --warm-starts "
                             "builtin,price:server:NAME-e1+server:NAME-e2+...` prices on Builtin's own states: "
                             "the epochs compared in iterations, step by step (docs/models.md)")
    parser.add_argument("--teacher", type=Path, metavar="CARD",
                        help="train on what this graph model (its card, e.g. models/NAME.json) answers at each "
                             "training and validation point instead of the recorded corrections: distillation "
                             "(training/teacher.py). The normalization stays the recorded targets', so --init "
                             "weights fit either way; the answers are kept in --cache")
    parser.add_argument("--second-pass", type=Path, metavar="CARD",
                        help="also train on every step as a second pass sees it: the warm start moved by what "
                             "this graph model (e.g. the --init weights' own card) serves there, the targets "
                             "what is left to correct (training/second_pass.py); the network is then served "
                             "with `passes: 2` (python -m training.card_variant CARD --passes 2). Its answers "
                             "are kept in --cache")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _network_arguments(parser) -> None:
    """The network's shape and how its output is served."""
    parser.add_argument("--combine", choices=("residual", "new-points", "replace"), default="residual",
                        help="serve the correction at every point (residual, default) or at new points only; "
                             "the solver loss then scores what is served: Box2D's warm start at persisting points; "
                             "replace: serve the answer itself (--targets face-labels)")
    parser.add_argument("--inputs", dest="input_scale", choices=("absolute", "scaled"), default="absolute",
                        help="absolute (default): the points' impulses, velocities and masses in N s, m/s and kg; "
                             "scaled: each over the step's own scale (deepcontact.channels.Step.scales: the median "
                             "body mass M, |g| dt, and M |g| dt for impulses), so that a heavier, stronger-pulled "
                             "or coarser-stepped world reads as the same problem")
    parser.add_argument("--width", type=int, default=DEFAULTS["width"], help="features per point (default %(default)s)")
    parser.add_argument("--rounds", type=int, default=DEFAULTS["rounds"],
                        help="message-passing rounds (default %(default)s); with --init from a network with "
                             "fewer, the new rounds follow its last and start as pass-throughs; from one with more, "
                             "its first rounds are kept and the rest dropped")
    parser.add_argument("--extra-inputs", default="", metavar="NAMES",
                        help="contact-point channels read after the standard ones, comma-separated (e.g. "
                             "last_correction_normal,last_correction_tangent; deepcontact/channels.py defines them); "
                             "with --init from a network without them, their first-layer weights start at 0")
    parser.add_argument("--pooled", action="store_true",
                        help="each round also reads the mean state of all points of the step, a graph-wide "
                             "summary; with --init from a network without it, the summary's weights start at 0")
    parser.add_argument("--layer-norm", action="store_true",
                        help="each round, and the decoder, reads the point states through a layer normalization "
                             "(pre-norm): what let sixteen rounds train on the GPU (docs/results.md)")
    parser.add_argument("--tied", action="store_true",
                        help="every round uses the same weights (one learned sweep, repeated --rounds times), so "
                             "the trained network can be exported at another depth (python -m lab.tied_rounds); "
                             "it helps at the depths it was trained at (--train-rounds), not past them; fine-tuning it "
                             "at sixteen rounds needed a lower --lr than the untied network (2e-4, not 5e-4)")
    parser.add_argument("--recall", action="store_true",
                        help="every round's update also reads the encoded inputs, so a deep tied network's last "
                             "rounds still see the step")
    parser.add_argument("--train-rounds", metavar="A-B",
                        help="with --tied: each training batch runs a round count drawn evenly from A to B "
                             "(validation and export run --rounds), so the one sweep learns to help at any depth")
    parser.add_argument("--symmetric", action="store_true",
                        help="train the mean of the network's answer and its mirror image's (the step reflected "
                             "left to right, answered, reflected back): the answer the loss scores is symmetric, "
                             "at twice the network's cost; serve it so (`python -m training.ensemble CARD --mirror`)")
    parser.add_argument("--probes", type=int, default=0, metavar="C",
                        help="every round also sends C trial impulses per point through the contact problem's "
                             "operator (m_eff J M^-1 J^T, exact) and reads back their effect (training/graph_model.py); "
                             "the export then takes the points' geometry and masses and the bodies' inverse masses, "
                             "which the server computes. With --init from a network without them, their reads start "
                             "at 0, so the network starts as exactly that one (default %(default)s: none)")
    parser.add_argument("--body-state", nargs="?", const="state", choices=("state", "sums"),
                        help="every body keeps a state across the rounds, updated from each round's sums "
                             "(training/graph_model.py); its points read that state ('state', the default when the "
                             "flag is given alone) or the round's sums plus it ('sums': with --init from a network "
                             "without one, the state starts at zero, so the network starts as exactly that one)")
    parser.add_argument("--global-state", action="store_true",
                        help="every step keeps a state across the rounds, grown from each round's mean of its "
                             "points, and its points read that state where --pooled reads the bare mean "
                             "(training/graph_model.py); implies --pooled")
    parser.add_argument("--attention", type=int, default=0, metavar="H",
                        help="each round also reads H heads of linear attention over the step's points: a mean "
                             "weighted by the match of each point's query and the others' keys (training/graph_model.py; "
                             "default %(default)s: none)")
    parser.add_argument("--passes", type=int, default=1, metavar="K",
                        help="train the network as a card with `passes: K` serves it: run K times, each pass "
                             "reading the channels at the warm start the last one made (recomputed inside the "
                             "training graph, training/second_pass.py) and the loss scoring the last; the card "
                             "gets passes K (default %(default)s)")


def _loss_arguments(parser) -> None:
    """What the network is trained to fit."""
    parser.add_argument("--targets", choices=tuple(TARGETS), default="final",
                        help="final (default): the correction to the impulses the recorded solve ended at; "
                             "oracle: to the step solved from zero to convergence (files from `generate --oracle`); "
                             "face: to the recorded solve's active set written as impulses (1 N s where a point "
                             "presses, +-1 N s along the tangent where it slides; friction read as the thesis "
                             "world's 0.5): a classifier of the points, read back with `lab faces --pressing 0.5 "
                             "--share 1`; face-labels: the same labels, not as a correction to Box2D's warm start "
                             "(with --combine replace: an answer that does not depend on the world's scale of impulse)")
    parser.add_argument("--loss", choices=("mse", "relative", "mse-self-stress", "mse-sticking", "mse-moving",
                                           "relative-moving", "solver", "solver-log",
                                           "solver-projected", "solver-projected-max", "solver-projected-sweeps"),
                        default="solver",
                        help="mse: squared error of the correction at every point; relative: each point's error "
                             "over its own correction's size (+ 0.05 N s), so small corrections count as much as "
                             "large ones; mse-self-stress: mse with the error's self-stress (the part that moves no "
                             "body, training.graph_loss.self_stress_part) weighted by --self-stress-weight, since that "
                             "part holds most of a warm start's value and little of its size; mse-sticking: mse at the "
                             "points whose friction is inside its cone both in Box2D's warm start and in the solver's "
                             "end (the others weigh nothing), where the exact answer holds nearly all a warm start's "
                             "value; mse-moving: the squared net impulse and torque the error puts on each body "
                             "moving at 1 cm/s or more, per body (the others and the self-stress weigh nothing): "
                             "the moving bodies' motion, which admitted holds most of a warm start's value; "
                             "relative-moving: that summed per step over the same of the step's own correction "
                             "(each moving body counted at least 0.01 N s), so small corrections count as much; "
                             "solver (default): the residual "
                             "the solver's sweeps leave of the warm start's error after --sweeps sweeps "
                             "(training.graph_loss), each checkpoint scaled by Box2D's own warm start's; "
                             "solver-log: per step, the log of that residual over Box2D's warm start's; "
                             "solver-projected: the change the solver's sweeps, with their limits (normal >= 0, "
                             "friction cone), would still make after --sweeps sweeps from the served impulses, "
                             "each checkpoint scaled by Box2D's own warm start's; solver-projected-max: per step, "
                             "the log of the largest such change (a --norm p-norm) over Box2D's warm start's, the "
                             "quantity the stopping rule compares with 1e-4 N s; solver-projected-sweeps: that "
                             "log ratio times the sweeps per e-fold Box2D's warm start needs in that step "
                             "(between the first and last --sweeps), an estimate of the sweeps saved, so that "
                             "slow steps, which make the mean, count for more")
    parser.add_argument("--self-stress-weight", type=float, default=8.0, metavar="W",
                        help="mse-self-stress: weight of the error's self-stress against its part that moves the "
                             "bodies (default %(default)s: the self-stress is about an eighth of the correction's "
                             "square, docs/results.md)")
    parser.add_argument("--self-stress-iterations", type=int, default=80, metavar="K",
                        help="mse-self-stress: conjugate-gradient steps of the split (default %(default)s, which "
                             "leave about 2 %% of its size on validation batches; each costs about a Jacobi sweep)")
    parser.add_argument("--sweeps", default="16,64,256",
                        help="solver loss: sweep counts at which the residual is measured (default %(default)s)")
    parser.add_argument("--norm", type=int, choices=NORMS, default=8,
                        help="solver-projected-max and -sweeps: the p of the p-norm over a step's points that "
                             "stands in for their largest change (default %(default)s; a higher p is closer to the "
                             "maximum the stopping rule reads and passes gradients to fewer points)")
    parser.add_argument("--harm-weight", type=float, default=1.0, metavar="K",
                        help="solver-projected-max: multiply a step's score by K where it is above 0 (the warm "
                             "start worse than Box2D's by the loss), since such steps cost more iterations per unit "
                             "of score than others save (deepcontact lab surrogate; default %(default)s)")
    parser.add_argument("--order", choices=ORDERS, default="jacobi",
                        help="solver-projected losses: the order of their sweeps. jacobi (default): every point "
                             "from the same impulses, damped; gauss-seidel: the solver's own, point after point "
                             "(run colour by colour: points that share no moving body at once), undamped")
    parser.add_argument("--omega", type=float, default=None,
                        help="solver loss: damping of the sweeps; Jacobi's are stable below about 0.6 here "
                             "(default 0.5 for jacobi, 1 for gauss-seidel, as Box2D)")
    parser.add_argument("--tangent-weight", type=float, default=1.0,
                        help="weight of the tangent component in the loss (default %(default)s)")


def _schedule_arguments(parser) -> None:
    """The optimizer's schedule, its start and the training steps it sees."""
    parser.add_argument("--epochs", type=int, default=DEFAULTS["epochs"], help="maximum epochs (default %(default)s)")
    parser.add_argument("--batch-size", type=int, default=DEFAULTS["batch_size"],
                        help="steps per batch (default %(default)s)")
    parser.add_argument("--lr", type=float, default=DEFAULTS["lr"], help="peak learning rate (default %(default)s)")
    parser.add_argument("--patience", type=int, default=DEFAULTS["patience"],
                        help="stop after this many epochs without a better validation loss (default %(default)s)")
    add_seed_argument(parser, "weights, step order and step sampling (default 0)", default=0)
    parser.add_argument("--init", type=Path, metavar="WEIGHTS",
                        help="start from these weights (the .weights.npz an earlier run left in --cache) instead of "
                             "random ones, for more epochs on a new schedule; same --width and --rounds, and the same "
                             "--train files, whose mean and std the weights were trained against")
    parser.add_argument("--resume", type=Path, metavar="STATE",
                        help="after every epoch write the run's state (the weights, Adam's moments, the step "
                             "order's random state, the history) to this .npz, and if it exists when the run "
                             "starts, go on after the epoch it holds: a run stopped and started again with the same "
                             "arguments reaches the weights of one never stopped. Removed once the model is written")
    parser.add_argument("--draw", choices=("uniform", "iterations", "converged"), default="uniform",
                        help="how each batch's training steps are drawn: uniformly (default); in proportion to "
                             "the velocity iterations Box2D's own warm start took there, as recorded: the mean "
                             "iterations a step that the bench reports are mostly the hard steps', where the "
                             "same error reduction saves the most iterations; or uniformly among the steps "
                             "Box2D's solve ended under its iteration cap, whose recorded impulses are converged "
                             "(elsewhere the targets are an unconverged iterate). Not with --second-pass"),
    parser.add_argument("--mirror-augment", action="store_true",
                        help="reflect each training step left to right with probability 1/2 (every input and "
                             "target channel times its sign under the reflection, the solver's geometry "
                             "reflected): the worlds are symmetric, the network is not built to be")

def _count_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with --train-rounds or --sweeps, or None; sets args.round_counts and
    args.sweeps (sorted tuples of ints)."""
    args.round_counts = (args.rounds,)
    if getattr(args, "train_rounds", None):
        if not args.tied:
            return "--train-rounds needs --tied (an untied network has one weight set per round)"
        try:
            low, high = (int(x) for x in str(args.train_rounds).split("-"))
            if not 1 <= low <= high:
                raise ValueError
        except ValueError:
            return f"--train-rounds takes a range of round counts like 4-12, got {args.train_rounds!r}"
        args.round_counts = tuple(range(low, high + 1))
    try:
        args.sweeps = tuple(sorted({int(k) for k in str(args.sweeps).split(",")}))
        if args.sweeps[0] < 0:
            raise ValueError
    except ValueError:
        return f"--sweeps takes sweep counts >= 0 like 16,64,256, got {args.sweeps!r}"
    if args.loss == "solver-projected-sweeps" and len(args.sweeps) < 2:
        return ("--loss solver-projected-sweeps measures Box2D's pace between two --sweeps counts; "
                f"give two or more, got {args.sweeps}")
    return None


def _argument_problem(args: argparse.Namespace) -> str | None:
    """The first thing wrong with the arguments, in a sentence, or None; sets args.omega
    (its default depends on --order), args.sweeps (a sorted tuple) and args.inputs."""
    if args.out.suffix != ".onnx":
        return f"--out must name a .onnx file, got {args.out}"
    given = (*args.train, *args.val,
             *(p for p in (args.init, getattr(args, "teacher", None), getattr(args, "second_pass", None)) if p))
    missing = [str(p) for p in given if not p.exists()]
    if missing:
        return f"no such file: {', '.join(missing)}"
    if not args.harm_weight > 0:
        return f"--harm-weight must be > 0, got {args.harm_weight}"
    if not args.self_stress_weight >= 0 or args.self_stress_iterations < 1:
        return (f"--self-stress-weight must be >= 0 and --self-stress-iterations >= 1, got "
                f"{args.self_stress_weight} and {args.self_stress_iterations}")
    if args.order == "gauss-seidel" and args.loss not in BatchLoss.PROJECTED_LOSSES:
        return (f"--order gauss-seidel orders the sweeps of the {', '.join(BatchLoss.PROJECTED_LOSSES)} "
                f"losses, not --loss {args.loss}")
    if args.omega is None:
        args.omega = 1.0 if args.order == "gauss-seidel" else 0.5
    if not (0 < args.omega < 1 or (args.order == "gauss-seidel" and args.omega == 1)):
        return (f"--omega must lie between 0 and 1 (1 itself only for --order gauss-seidel), "
                f"got {args.omega}")
    if min(args.epochs, args.batch_size, args.width, args.rounds, args.patience) < 1:
        return "--epochs, --batch-size, --width, --rounds and --patience must be >= 1"
    if getattr(args, "probes", 0) < 0:
        return f"--probes must be 0 (none) or more, got {args.probes}"
    heads = getattr(args, "attention", 0)
    if heads < 0 or (heads and args.width % heads):
        return f"--attention must be 0 (none) or a number of heads that divides --width {args.width}, got {heads}"
    if getattr(args, "draw", "uniform") != "uniform" and getattr(args, "second_pass", None) is not None:
        return f"--draw {args.draw} weighs the recorded steps; --second-pass adds steps that were not recorded"
    problem = _count_problem(args)
    if problem:
        return problem
    extra = tuple(n for n in str(args.extra_inputs).split(",") if n)
    bad = [n for n in extra if n not in CHANNELS or CHANNELS[n].source != "contacts" or n in GRAPH_INPUTS]
    if bad or len(set(extra)) != len(extra):
        return (f"--extra-inputs takes contact-point channels not already read ({', '.join(GRAPH_INPUTS)}), "
                f"each once; got {args.extra_inputs!r}")
    if (getattr(args, "targets", "final") == "face-labels") != (args.combine == "replace"):
        return (f"--targets face-labels is served as it is answered, --combine replace, and only it; got "
                f"--targets {getattr(args, 'targets', 'final')} with --combine {args.combine}")
    scaled = getattr(args, "input_scale", "absolute")
    if scaled == "scaled" and (args.loss.startswith("solver") or getattr(args, "passes", 1) > 1
                               or getattr(args, "teacher", None) or getattr(args, "second_pass", None)):
        return ("--inputs scaled trains with the losses on the points' targets (mse, relative, ...), one pass, "
                "no teacher or second pass: those read the absolute inputs")
    args.inputs = (SCALED_GRAPH_INPUTS if scaled == "scaled" else GRAPH_INPUTS) + extra
    passes = getattr(args, "passes", 1)
    if passes < 1 or (passes > 1 and args.combine != "residual"):
        return f"--passes must be >= 1, and above 1 only with --combine residual; got {passes}, {args.combine}"
    if passes > 1:
        try:
            check_second_pass_inputs(args.inputs)
        except SecondPassError as exc:
            return f"--passes {passes}: {exc}"
    return None


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    problem = _argument_problem(args)
    if problem:
        print(f"train-graph: {problem}", file=sys.stderr)
        return 2
    command = "deepcontact train-graph " + " ".join(shlex.quote(a) for a in sys.argv[2:])
    t0 = time.perf_counter()
    targets = TARGETS[getattr(args, "targets", "final")]
    sets = ((args.train, args.max_steps_per_file), (args.val, args.max_val_steps))
    try:
        train, val = ([cached_graph_set(p, most, args.seed, args.cache, args.quiet, targets, args.inputs) for p in paths]
                      for paths, most in sets)
        recorded = train
        if getattr(args, "teacher", None) is not None:
            teacher = Teacher.load(args.teacher)
            train, val = ([_taught(g, p, most, teacher, args) for g, p in zip(gs, paths)]
                          for gs, (paths, most) in zip((train, val), sets))
        if getattr(args, "second_pass", None) is not None:
            first = _first_pass(args.second_pass)
            train, val = ([*gs, *(_moved(g, p, most, first, args) for g, p in zip(gs, paths))]
                          for gs, (paths, most) in zip((train, val), sets))
    except (GridDataError, ValueError) as exc:  # ValueError: --targets oracle on a file without the oracle,
        print(f"train-graph: {exc}", file=sys.stderr)  # or a --teacher that cannot answer these steps
        return 2
    draw = None
    if getattr(args, "draw", "uniform") == "iterations":
        # A step with no recorded iteration (a file written without them) is drawn as a step with one.
        draw = [np.maximum(step_iterations(p, args.max_steps_per_file, args.seed), 1) for p in args.train]
    elif getattr(args, "draw", "uniform") == "converged":
        draw = [step_converged(p, args.max_steps_per_file, args.seed).astype(np.float64) for p in args.train]
        if not all(d.any() for d in draw):
            print("train-graph: --draw converged: a training file has no step that Box2D's solve ended under "
                  "its cap", file=sys.stderr)
            return 2
    if draw is not None:
        if any(len(d) != len(g) for d, g in zip(draw, train)):  # the cache and the file must hold the same steps
            print("train-graph: a training file's steps and its cached graphs differ in number; delete the "
                  "cache (--cache) and run again", file=sys.stderr)
            return 2
    read_seconds = time.perf_counter() - t0
    try:
        card = fit(train, val, args, command=command, read_seconds=read_seconds,
                   sources=[str(p) for p in args.train], val_sources=[str(p) for p in args.val],
                   normalize_with=recorded, draw=draw)
    except TrainingDiverged as exc:
        print(f"train-graph: {exc}", file=sys.stderr)
        return 1
    except (WeightsMismatch, ResumeMismatch) as exc:
        print(f"train-graph: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}: validation loss "
          f"{card.validation['loss']:.4f} (no correction: {card.validation['loss_no_correction']:.4f}), "
          f"{card.training['train_seconds']:.0f} s training")
    return 0


def _cache_name(path: Path, max_steps: int | None, seed: int, targets: tuple[str, ...],
                inputs: tuple[str, ...]) -> str:
    """STEM-KEY: which steps of which file, read with which channels, a cache file holds."""
    st = path.stat()
    key = json.dumps([CACHE_VERSION, str(path.resolve()), st.st_size, int(st.st_mtime), max_steps, seed,
                      inputs, targets])
    return f"{path.stem}-{hashlib.sha1(key.encode()).hexdigest()[:12]}"


def cached_graph_set(path: Path, max_steps: int | None, seed: int, cache: Path, quiet: bool,
            targets: tuple[str, ...] = GRAPH_TARGETS, inputs: tuple[str, ...] = GRAPH_INPUTS) -> GraphSet:
    """The file's contact graphs (at most max_steps of its steps, drawn with seed), read once and
    kept as .npz under `cache`: what train-graph trains and validates on."""
    target = cache / f"{_cache_name(path, max_steps, seed, targets, inputs)}.npz"
    if target.exists():
        return GraphSet.load(target)
    bar = None if quiet else _bar(None, f"graphs {path.name}")
    try:
        gs = build_graph_set(path, inputs, targets, max_steps=max_steps, seed=seed, progress=bar)
    finally:
        if bar is not None:
            bar.close()
    gs.save(target)
    return gs


def _taught(gs: GraphSet, path: Path, max_steps: int | None, teacher: Teacher, args) -> GraphSet:
    """gs with --teacher's answers as targets, kept under --cache beside gs's own file."""
    name = _cache_name(path, max_steps, args.seed, gs.target_names, gs.inputs)
    bar = None if args.quiet else _bar(len(gs), f"teacher on {path.name}")
    try:
        return taught(gs, teacher, Path(args.cache) / f"{name}-teacher-{teacher.digest}.npz", progress=bar)
    finally:
        if bar is not None:
            bar.close()


def _first_pass(card_path: Path) -> Teacher:
    """--second-pass's card, refused unless what it serves is Box2D's warm start plus its answer."""
    first = Teacher.load(card_path)
    card = first.card
    if card.combine != "residual" or card.correction_scale != 1.0 or card.correction_threshold != 0.0 \
            or card.passes != 1:
        raise SecondPassError(f"{card_path}: --second-pass moves the warm start by what the card serves, Box2D's "
                              f"plus its correction; this card serves combine {card.combine!r}, scale "
                              f"{card.correction_scale:g}, threshold {card.correction_threshold:g}, "
                              f"{card.passes} pass(es)")
    return first


def _moved(gs: GraphSet, path: Path, max_steps: int | None, first: Teacher, args) -> GraphSet:
    """gs as --second-pass's second pass sees it; the first pass's answers kept under --cache."""
    check_second_pass(gs)
    name = _cache_name(path, max_steps, args.seed, gs.target_names, gs.inputs)
    bar = None if args.quiet else _bar(len(gs), f"first pass on {path.name}")
    try:
        answered = taught(gs, first, Path(args.cache) / f"{name}-teacher-{first.digest}.npz", progress=bar)
    finally:
        if bar is not None:
            bar.close()
    return moved(gs, answered.targets)


def normalization(train: list[GraphSet]) -> dict[str, tuple[float, float]]:
    """Per-channel (mean, std) over every training point; a constant channel gets std 1."""
    feats = np.concatenate([g.features for g in train]).astype(np.float64)
    targs = np.concatenate([g.targets for g in train]).astype(np.float64)
    out = {}
    for names, values in ((train[0].inputs, feats), (train[0].target_names, targs)):
        mean, std = values.mean(axis=0), values.std(axis=0)
        for j, n in enumerate(names):
            out[n] = (float(mean[j]), float(std[j]) if std[j] > 1e-12 else 1.0)
    return out


@dataclasses.dataclass(frozen=True)
class Scaling:
    """The training files' per-channel mean and std, (F,) for the inputs and (T,) for the
    targets, float32: what the card's GridSpec carries and the server undoes."""

    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: np.ndarray
    out_std: np.ndarray

    @classmethod
    def of(cls, spec: GridSpec) -> "Scaling":
        return cls(*spec.normalization_arrays(spec.inputs), *spec.normalization_arrays(spec.targets))

    def batch(self, gs: GraphSet, steps, *, colour: bool = False, reflect: np.ndarray | None = None) -> tuple:
        """Steps of gs as one normalized batch: points (P, F), ends (P, 2), dynamic (B, 1),
        targets (P, T), geometry (P, 8), masses (P, 2), inverse (B, 2), step_of (P,) int32
        (each point's step within the batch), colour (P,) int32 (training.graph_loss.colour_points
        with `colour`, for --order gauss-seidel; else 0), speed (B,) m/s.
        reflect: (S,) bool per step, those steps reflected left to right (--mirror-augment)."""
        from training.graph_loss import colour_points

        f, t, e, d = gs.batch(steps)
        counts = np.diff(gs.point_offsets)[np.asarray(steps)]
        step_of = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
        geometry, masses, inverse = gs.solver_batch(steps)
        if reflect is not None and np.any(reflect):
            at = np.asarray(reflect, bool)[step_of]  # (P,) the points of reflected steps
            f[at] *= mirror_signs(gs.inputs)
            t[at] *= mirror_signs(gs.target_names)
            geometry[at] *= MIRROR_GEOMETRY
        colours = colour_points(e, inverse) if colour else np.zeros(len(e), np.int32)
        return ((f - self.in_mean) / self.in_std, e, d, (t - self.out_mean) / self.out_std,
                geometry, masses, inverse, step_of, colours, gs.body_speeds(steps))


class BatchLoss:
    """A batch's loss for --loss: batch_loss(points, ends, dynamic, y, geometry, masses,
    inverse, step_of, colour, speed) -> (losses, weights), the loss being sum(losses) / sum(weights);
    per point for mse, relative, solver and solver-projected, per step for solver-log
    and solver-projected-max and relative-moving, per body for mse-moving.

    points (P, F) and y (P, T) are normalized (Scaling); `inputs` names the points'
    columns and `targets` y's. The solver losses score the error a served correction leaves,
    in N s."""

    POINT_LOSSES = ("mse", "relative")
    PROJECTED_LOSSES = ("solver-projected", "solver-projected-max", "solver-projected-sweeps")

    def __init__(self, net, args, scaling: Scaling, residual_scales: list[float], inputs: tuple[str, ...],
                 targets: tuple[str, ...] = GRAPH_TARGETS):
        import tensorflow as tf

        self.tf, self.net, self.args = tf, net, args
        # Read by a network with probes only; the tests score plain functions as networks.
        self.probes = getattr(getattr(net, "config", None), "probes", 0)
        self.out_mean, self.out_std = scaling.out_mean, scaling.out_std
        self.in_mean, self.in_std = scaling.in_mean, scaling.in_std
        self.mirror_in = mirror_signs(inputs)
        self.mirror_out = mirror_signs(targets)
        self.new_column = inputs.index("new_point")
        # Read by the solver losses, which take absolute inputs only (--inputs scaled refuses them).
        absolute = "builtin_normal" in inputs
        self.builtin_columns = [inputs.index("builtin_normal"), inputs.index("builtin_tangent")] if absolute else None
        self.velocity_columns = [inputs.index("vn"), inputs.index("vt")] if absolute else None
        if getattr(args, "passes", 1) > 1:  # which inputs move with the warm start, and how (second_pass)
            self.moves_with_warm, self.moves_with_velocity, self.moves_with_jacobi = (
                tf.constant(m, tf.float32) for m in second_pass_moves(inputs))
        self.loss_weight = tf.constant([1.0] + [args.tangent_weight] * (len(self.out_mean) - 1), tf.float32)
        # Solver loss: each checkpoint's mean squared residual, divided by what Box2D's
        # own warm start (no correction) leaves there on the training data, so each counts alike.
        self.scales = tf.constant(residual_scales, tf.float32)

    def predict(self, points, ends, dynamic, step_of, rounds=None, physics=None):
        """The correction the loss scores, (P, T) normalized: the network's, or with --symmetric
        the mean of it and its mirror image's (the reflection x -> -x of every channel, taken in
        raw units, since the normalization's means do not change sign). physics: (geometry,
        masses, inverse), read by a network with probes only."""
        depth = {} if rounds is None else {"rounds": rounds}  # only a tied network is asked for a depth
        if self.probes:
            depth["physics"] = physics
        pred = self.net(points, ends, dynamic, step_of, **depth)
        if not getattr(self.args, "symmetric", False):
            return pred
        mirrored_in = ((points * self.in_std + self.in_mean) * self.mirror_in - self.in_mean) / self.in_std
        if self.probes:
            geometry, masses, inverse = physics
            depth["physics"] = (geometry * MIRROR_GEOMETRY, masses, inverse)
        answer = self.net(mirrored_in, ends, dynamic, step_of, **depth) * self.out_std + self.out_mean
        return 0.5 * (pred + (answer * self.mirror_out - self.out_mean) / self.out_std)

    def __call__(self, points, ends, dynamic, y, geometry, masses, inverse, step_of, colour, speed, rounds=None):
        """The batch's (losses, weights); rounds, how many the network runs (a tied one's choice)."""
        pred = self.predict(points, ends, dynamic, step_of, rounds, (geometry, masses, inverse))
        for _ in range(getattr(self.args, "passes", 1) - 1):
            pred = self._again(pred, points, ends, dynamic, geometry, masses, inverse, step_of)
        if self.args.loss in self.POINT_LOSSES:
            return self._at_points(pred, y)
        if self.args.loss == "mse-self-stress":
            return self._split(pred, y, ends, geometry, inverse)
        if self.args.loss == "mse-sticking":
            return self._sticking(points, pred, y, step_of)
        if self.args.loss in ("mse-moving", "relative-moving"):
            return self._moving(pred, y, ends, geometry, inverse, speed, step_of)
        error, builtin_error = self._errors(points, pred, y)
        solver = (ends, geometry, masses, inverse, step_of)
        if self.args.loss in self.PROJECTED_LOSSES:
            return self._projected(points, *solver, colour, error, builtin_error)
        return self._unconstrained(*solver, error, builtin_error)

    def _again(self, pred, points, ends, dynamic, geometry, masses, inverse, step_of):
        """The correction after one more pass, (P, T) normalized: the network asked again at the
        warm start pred made, its inputs moved as training.second_pass.moved moves them, the
        gradient flowing through both passes."""
        from training.graph_loss import apply_delassus

        correction = pred * self.out_std + self.out_mean  # N s
        velocity = apply_delassus(correction, ends, geometry, inverse)  # m/s
        moved = points + (correction @ self.moves_with_warm + velocity @ self.moves_with_velocity
                          - (masses * velocity) @ self.moves_with_jacobi) / self.in_std
        answer = self.predict(moved, ends, dynamic, step_of, physics=(geometry, masses, inverse)) * self.out_std \
            + self.out_mean
        return (correction + answer - self.out_mean) / self.out_std

    def _at_points(self, pred, y):
        """mse and relative: each point's squared error, normalized units."""
        tf = self.tf
        if self.args.loss == "mse":
            per_point = tf.reduce_sum(tf.square(pred - y) * self.loss_weight, axis=1)
        else:
            # Each point's error relative to its own correction (floored at RELATIVE_FLOOR):
            # small corrections, where a warm start's value lies, count as much as large ones.
            target = y * self.out_std + self.out_mean
            per_point = tf.reduce_sum(tf.square((pred - y) * self.out_std / (tf.abs(target) + RELATIVE_FLOOR))
                                      * self.loss_weight, axis=1)
        return per_point, tf.ones_like(per_point)

    def _split(self, pred, y, ends, geometry, inverse):
        """mse-self-stress: each point's squared error, normalized units, its self-stress part
        (in N s, where the split is defined) weighted by --self-stress-weight."""
        tf = self.tf
        from training.graph_loss import self_stress_part

        error = (pred - y) * self.out_std
        stress = self_stress_part(error, ends, geometry, inverse, iterations=self.args.self_stress_iterations)
        moving = (error - stress) / self.out_std
        stress = stress / self.out_std
        per_point = tf.reduce_sum((tf.square(moving) + self.args.self_stress_weight * tf.square(stress))
                                  * self.loss_weight, axis=1)
        return per_point, tf.ones_like(per_point)

    def _moving(self, pred, y, ends, geometry, inverse, speed, step_of):
        """mse-moving: the squared net impulse and torque the error puts on each dynamic body
        moving at REST_SPEED or more (N s and N m s, over the normal target's std), per body;
        the other bodies and the error's self-stress weigh nothing. The motion the admission
        of the moving bodies needs (docs/results.md, "Whose motion: the moving bodies'").
        relative-moving: the same summed per step, over the same of the step's correction."""
        tf = self.tf
        from deepcontact.kinematics import REST_SPEED
        from training.graph_loss import body_impulses

        n_bodies = tf.shape(inverse)[0]
        moving = tf.cast((inverse[:, 0] > 0) & (speed >= REST_SPEED), tf.float32)

        def pushes(impulses):  # (P, 2) N s -> (B,) (N s)^2 at the moving bodies, 0 elsewhere
            force, torque = body_impulses(impulses, ends, geometry, n_bodies)
            return (tf.reduce_sum(tf.square(force), axis=1) + tf.square(torque)) * moving

        error = pushes((pred - y) * self.out_std)
        if self.args.loss == "mse-moving":
            return error / float(self.out_std[0]) ** 2, moving
        # relative-moving: per step, over the step's own correction's push on its moving bodies
        # (each such body counted at least MOVING_FLOOR N s), so a step whose bodies barely need
        # correcting, where the iterations are, asks for an error as small as its correction.
        step_of_body = tf.maximum(tf.math.unsorted_segment_max(tf.concat([step_of, step_of], 0),
                                                               tf.concat([ends[:, 0], ends[:, 1]], 0), n_bodies), 0)
        n_steps = tf.reduce_max(step_of) + 1
        target = pushes(y * self.out_std + self.out_mean)
        per_step = tf.math.unsorted_segment_sum(tf.stack([error, target, moving], axis=1), step_of_body, n_steps)
        weight = tf.cast(per_step[:, 2] > 0, tf.float32)
        return per_step[:, 0] / (per_step[:, 1] + per_step[:, 2] * MOVING_FLOOR ** 2 + (1.0 - weight)), weight

    def _sticking(self, points, pred, y, step_of):
        """mse-sticking: mse at the points whose friction stays inside its cone (below
        STICKING_SHARE of mu times the normal impulse, or not pressing) in Box2D's warm start
        and in the solver's end; the other points weigh nothing."""
        tf = self.tf
        from training.graph_loss import friction_bounds

        raw = points * self.in_std + self.in_mean
        builtin = tf.gather(raw, self.builtin_columns, axis=1)
        solution = builtin + (y * self.out_std + self.out_mean)  # the solver's end, N s
        mu = friction_bounds(solution, step_of)

        def at_cone(lam):
            # mu is 0 in a step without friction: nothing there is held back by a cone.
            return (lam[:, 0] > 1e-4) & (mu > 0.0) & (tf.abs(lam[:, 1]) >= STICKING_SHARE * mu * lam[:, 0])

        sticking = tf.cast(~(at_cone(builtin) | at_cone(solution)), tf.float32)
        per_point = tf.reduce_sum(tf.square(pred - y) * self.loss_weight, axis=1) * sticking
        return per_point, sticking

    def _errors(self, points, pred, y):
        """(error, builtin_error), (P, T) N s: what the served warm start and Box2D's own miss
        of the solver's end."""
        tf = self.tf
        error = (pred - y) * self.out_std  # the served correction minus the solver's
        builtin_error = -(y * self.out_std + self.out_mean)  # Box2D's warm start misses the whole correction
        if self.args.combine == "new-points":
            # Served at new points only; persisting points keep Box2D's warm start.
            c = self.new_column
            new_point = points[:, c] * self.in_std[c] + self.in_mean[c]
            error = tf.where(new_point[:, None] > 0.5, error, builtin_error)
        return error, builtin_error

    def _unconstrained(self, ends, geometry, masses, inverse, step_of, error, builtin_error):
        """solver and solver-log: Jacobi sweeps of the problem without its limits, on the error."""
        tf, args = self.tf, self.args
        from training.graph_loss import residuals_after

        def squares(e):
            rs = residuals_after(e, ends, geometry, masses, inverse, sweeps=args.sweeps, omega=args.omega)
            return [tf.reduce_sum(tf.square(r) * self.loss_weight, axis=1) for r in rs]

        if args.loss == "solver":
            per_point = tf.add_n([r / self.scales[j] for j, r in enumerate(squares(error))]) / len(args.sweeps)
            return per_point, tf.ones_like(per_point)
        # solver-log: per step, log(what the model leaves / what Box2D's warm start leaves), the
        # iterations saved being about proportional to it (the solver removes a fixed share per sweep).
        n_steps = tf.reduce_max(step_of) + 1
        per_step = tf.add_n([
            tf.math.log((tf.math.unsorted_segment_sum(m, step_of, n_steps) + LOG_FLOOR)
                        / (tf.math.unsorted_segment_sum(b, step_of, n_steps) + LOG_FLOOR))
            for m, b in zip(squares(error), squares(builtin_error))]) / len(args.sweeps)
        return per_step, tf.ones_like(per_step)

    def _projected(self, points, ends, geometry, masses, inverse, step_of, colour, error, builtin_error):
        """solver-projected and -max: projected sweeps of the whole problem from the served impulses,
        in Jacobi's order or, with --order gauss-seidel, in the solver's (colour by colour)."""
        tf, args = self.tf, self.args
        from training.graph_loss import (friction_bounds, gauss_seidel_changes_after, projected_changes_after,
                                         step_log_norms)

        raw = points * self.in_std + self.in_mean
        builtin = tf.gather(raw, self.builtin_columns, axis=1)
        solution = builtin - builtin_error  # Box2D's warm start plus the solver's correction
        v_free, mu = tf.gather(raw, self.velocity_columns, axis=1), friction_bounds(solution, step_of)

        def changes_from(start):
            if getattr(args, "order", "jacobi") == "gauss-seidel":
                return gauss_seidel_changes_after(start, v_free, mu, ends, geometry, masses, inverse, colour,
                                                  sweeps=args.sweeps, omega=args.omega)
            return projected_changes_after(start, v_free, mu, ends, geometry, masses, inverse,
                                           sweeps=args.sweeps, omega=args.omega)

        changes = changes_from(solution + error)
        if args.loss in ("solver-projected-max", "solver-projected-sweeps"):
            # The solver stops when a sweep's largest change falls below 1e-4 N s and removes a
            # roughly fixed share per sweep, so the iterations a warm start saves go with the log
            # of that largest change; a p-norm per step (--norm, 8 by default) is a max that
            # passes gradients to more than one point.
            n_steps = tf.reduce_max(step_of) + 1

            def log_norm(c):
                return step_log_norms(c, step_of, n_steps, p=args.norm, weight=self.loss_weight)

            builtin_changes = changes_from(solution + builtin_error)
            per_step = tf.add_n([log_norm(m) - log_norm(b) for m, b in
                                 zip(changes, builtin_changes)]) / len(args.sweeps)
            if args.loss == "solver-projected-max":
                # A step the warm start makes worse costs more iterations per unit of this score
                # than a step it makes better saves (lab surrogate): --harm-weight K > 1 says so.
                harm = args.harm_weight
                if harm != 1.0:
                    per_step = tf.where(per_step > 0, harm * per_step, per_step)
                return per_step, tf.ones_like(per_step)
            # Sweeps saved ~ the log ratio times the sweeps the step needs per e-fold, which
            # Box2D's warm start shows between the first and last checkpoint: a slow step (the
            # hundreds of iterations that make the mean) counts for more than a quick one.
            # At most one e-fold's floor: a step whose changes hardly fall (already below the stopping
            # rule, about 1 in 8 of them, or stalled) weighs `span`, about 3 times the median step.
            fall = log_norm(builtin_changes[0]) - log_norm(builtin_changes[-1])
            span = float(args.sweeps[-1] - args.sweeps[0])
            weight = tf.stop_gradient(span / tf.maximum(fall, 1.0))
            return per_step * weight, weight
        per_point = tf.add_n([tf.reduce_sum(tf.square(c) * self.loss_weight, axis=1) / self.scales[j]
                              for j, c in enumerate(changes)]) / len(args.sweeps)
        return per_point, tf.ones_like(per_point)


@dataclasses.dataclass
class Fitted:
    """What a training loop leaves: the best epoch's weights and how it got there."""

    weights: dict[str, np.ndarray]
    loss: float  # best validation loss
    epoch: int
    history: list  # [epoch, mean training loss, validation loss] per epoch
    stop_reason: str
    seconds: float
    resumed_after: list = dataclasses.field(default_factory=list)  # the epochs a --resume went on after


def fit(train: list[GraphSet], val: list[GraphSet], args, *, command: str, read_seconds: float,
        sources: list[str], val_sources: list[str], normalize_with: list[GraphSet] | None = None,
        draw: list[np.ndarray] | None = None) -> ModelCard:
    """Train a ContactGraphNet on `train`, keep the epoch best on `val`, and write the
    ONNX file and its card to args.out (see the module docstring). The normalization is
    `normalize_with`'s (default `train`'s): the recorded sets when a teacher answered `train`.
    draw: per training set, (S,) weights its steps are drawn in proportion to (None: uniformly;
    a zero weight: never)."""
    from training.graph_model import ContactGraphNet, GraphConfig

    spec = GridSpec.thesis(inputs=train[0].inputs, targets=train[0].target_names,
                           normalization=normalization(normalize_with or train))
    scaling = Scaling.of(spec)
    config = GraphConfig(in_channels=len(spec.inputs), out_channels=len(spec.targets), width=args.width,
                         rounds=args.rounds, pooled=args.pooled or getattr(args, "global_state", False),
                         global_state=getattr(args, "global_state", False),
                         layer_norm=getattr(args, "layer_norm", False), tied=getattr(args, "tied", False),
                         recall=getattr(args, "recall", False), probes=getattr(args, "probes", 0),
                         body_state=bool(getattr(args, "body_state", None)),
                         body_plus_sums=getattr(args, "body_state", None) == "sums",
                         attention=getattr(args, "attention", 0))
    if args.init is not None:
        net = ContactGraphNet(config, initial_weights(args.init, config))
    else:
        net = ContactGraphNet(config, seed=args.seed)
        # Start from Box2D's own warm start: the last layer's kernel is 0, its bias a zero correction.
        net.variables["decode1/bias"].assign((0 - scaling.out_mean) / scaling.out_std)
    net.tf.random.set_seed(args.seed)
    residual_scales = _residual_scales(train, args) if args.loss in ("solver", "solver-projected") else [1.0]
    batch_loss = BatchLoss(net, args, scaling, residual_scales, spec.inputs, spec.targets)
    describe = _CardParts(spec, args, command=command, read_seconds=read_seconds, sources=sources,
                          val_sources=val_sources, train=train, val=val)
    def checkpoint(epoch: int, fitted_so_far: "Fitted") -> None:
        _write_checkpoint(net, epoch, fitted_so_far, describe, scaling, val)
    keep_epochs = getattr(args, "checkpoints", None) is not None
    fitted, validate = _train(net, train, val, args, scaling, batch_loss,
                              on_epoch=checkpoint if keep_epochs else None, draw=draw)
    card = _write(net, fitted, validate, describe, scaling, val)
    if getattr(args, "resume", None) is not None:
        Path(args.resume).unlink(missing_ok=True)  # the run is done: a new one with these arguments starts over
    return card


def initial_weights(path: Path, config) -> dict[str, np.ndarray]:
    """Weights saved by an earlier run, checked against the network `config` describes."""
    from training.graph_model import init_weights

    with np.load(path, allow_pickle=False) as f:
        weights = {k: f[k] for k in f.files}
    fresh = init_weights(config)
    expected = {k: v.shape for k, v in fresh.items()}
    rounds = sum(1 for k in weights if k.endswith("_update1/kernel"))
    if not config.tied and 0 < rounds < config.rounds and all(k in expected for k in weights):
        # A network with fewer rounds: the new ones follow its last, their update's last layer at
        # zero, so each passes its input through (the residual) and the network starts as exactly
        # the one it grew from; their other layers start random, so gradients reach them.
        for r in range(rounds, config.rounds):
            for k in (k for k in fresh if k.startswith(f"round{r}_")):
                weights[k] = np.zeros_like(fresh[k]) if k.startswith(f"round{r}_update1/") else fresh[k]
    if not config.tied and rounds > config.rounds > 0 and all(k in weights for k in expected):
        # A network with more rounds: its first ones kept, the rest dropped. Each round adds its
        # update to the points' state (the residual), so the kept rounds compute what they did and
        # the decoder, trained on from here, reads the state after fewer of them.
        weights = {k: v for k, v in weights.items()
                   if not (k.startswith("round") and int(k[len("round"):k.index("_")]) >= config.rounds)}
    k = "encode0/kernel"
    if k in weights and weights[k].shape[0] < config.in_channels and weights[k].shape[1:] == expected[k][1:]:
        # A network that read fewer inputs (--extra-inputs): the new ones get zero rows in the
        # first layer, so the network starts as exactly the one it grew from.
        v = weights[k]
        weights[k] = np.concatenate([v, np.zeros((config.in_channels - v.shape[0], v.shape[1]), v.dtype)])
    if config.probes and not any(k.endswith("_probe/kernel") for k in weights):
        # A network without probes: each round gains its probe layer (random, so gradients reach
        # it) and its update zero rows for the probes' reads (the last 2C), so the network starts
        # as exactly the one it grew from.
        for k, v in list(weights.items()):
            if k.endswith("_update0/kernel") and k in expected and v.shape[0] == expected[k][0] - 2 * config.probes:
                weights[k] = np.concatenate([v, np.zeros((2 * config.probes, v.shape[1]), v.dtype)])
        weights.update({k: v for k, v in fresh.items() if "_probe/" in k})
    if config.body_plus_sums and not any("_body0/" in k for k in weights):
        # A network without a body state: each round gains its state layers, the last at zero, so
        # the state stays zero and the points read the bare sums: exactly the network it grew from.
        weights.update({k: np.zeros_like(v) if "_body1/" in k else v for k, v in fresh.items() if "_body" in k})
    if config.pooled:
        # A network without the summary: its update layers gain zero rows for it, so the
        # pooled network starts as exactly that network.
        for k, v in list(weights.items()):
            if k.endswith("_update0/kernel") and k in expected and v.shape[0] < expected[k][0] == 4 * config.width:
                weights[k] = np.concatenate([v, np.zeros((expected[k][0] - v.shape[0], v.shape[1]), v.dtype)])
    got = {k: v.shape for k, v in weights.items()}
    if got != expected:
        raise WeightsMismatch(f"{path} holds another network's weights than --width {config.width} --rounds "
                         f"{config.rounds}{' --tied' if config.tied else ''}{' --recall' if config.recall else ''}"
                         f"{' --pooled' if config.pooled else ''}{f' --probes {config.probes}' if config.probes else ''}"
                         f"{' --layer-norm' if config.layer_norm else ''}{(' --body-state sums' if config.body_plus_sums else ' --body-state') if config.body_state else ''}"
                         f"{' --global-state' if config.global_state else ''}"
                         f"{f' --attention {config.attention}' if config.attention else ''} "
                         f"with {config.in_channels} inputs")
    return weights


def _compiled_steps(net, batch_loss, lr: float, round_counts: tuple[int, ...] = ()):
    """(optimizer, train_steps, val_step): Adam at `lr`, and traced functions of a
    normalized batch (Scaling.batch): train_steps[K] applies one update with the network
    running K rounds (one K, config.rounds, unless a tied network trains at several) and
    returns the batch's loss; val_step, at config.rounds, returns (sum of losses, sum of weights)."""
    tf = net.tf
    optimizer = tf.keras.optimizers.Adam(learning_rate=lr)
    # Adam's moments made now, not inside the first traced step: a tf.function that creates
    # variables is traced twice, and the solver losses' graphs take minutes to trace.
    optimizer.build(net.trainable)
    # The network's first three inputs; a batch carries the physics a network with probes reads anyway.
    spec_in = net.signature()[:3] + [tf.TensorSpec((None, net.config.out_channels), tf.float32),
                                 tf.TensorSpec((None, 8), tf.float32), tf.TensorSpec((None, 2), tf.float32),
                                 tf.TensorSpec((None, 2), tf.float32), tf.TensorSpec((None,), tf.int32),
                                 tf.TensorSpec((None,), tf.int32), tf.TensorSpec((None,), tf.float32)]

    def train_step_at(rounds: int):
        @tf.function(input_signature=spec_in)
        def train_step(*batch):
            with tf.GradientTape() as tape:
                losses, weights = batch_loss(*batch, rounds=rounds if len(round_counts) > 1 else None)
                # A batch may weigh nothing (mse-sticking: every point slides; mse-moving: no body
                # moves): no loss, no step.
                loss = tf.reduce_sum(losses) / tf.maximum(tf.reduce_sum(weights), 1e-12)
            optimizer.apply_gradients(zip(tape.gradient(loss, net.trainable), net.trainable))
            return loss
        return train_step

    @tf.function(input_signature=spec_in)
    def val_step(*batch):
        losses, weights = batch_loss(*batch)
        return tf.reduce_sum(losses), tf.reduce_sum(weights)

    if len(round_counts) > 1:
        # Each depth's step is traced once, but TensorFlow counts the traces of one Python function
        # together and warns of "excessive retracing"; nothing is retraced.
        import logging

        logging.getLogger("tensorflow").setLevel(logging.ERROR)
    return optimizer, {k: train_step_at(k) for k in (round_counts or (net.config.rounds,))}, val_step


def _train(net, train: list[GraphSet], val: list[GraphSet], args, scaling: Scaling, batch_loss, on_epoch=None,
           draw: list[np.ndarray] | None = None):
    """Adam on a cosine schedule over args.epochs, stopping after args.patience epochs
    without a better validation loss. Returns (Fitted, validate), validate() scoring
    the net's current weights on `val`. on_epoch(epoch, fitted) is called after each
    epoch's validation, the net holding that epoch's weights."""
    round_counts = getattr(args, "round_counts", (net.config.rounds,))
    optimizer, train_steps, val_step = _compiled_steps(net, batch_loss, args.lr, round_counts)
    colour = getattr(args, "order", "jacobi") == "gauss-seidel"
    mirror = getattr(args, "mirror_augment", False)

    def validate() -> float:
        total, count = 0.0, 0.0
        for gs in val:
            for k in range(0, len(gs), 64):
                loss_sum, weight_sum = val_step(*scaling.batch(gs, np.arange(k, min(k + 64, len(gs))), colour=colour))
                total += float(loss_sum)
                count += float(weight_sum)
        return total / count

    rng = np.random.default_rng(args.seed)
    batches = [(i, chunk) for i, gs in enumerate(train)
               for chunk in np.array_split(np.arange(len(gs)), max(1, len(gs) // args.batch_size))]
    total_steps = args.epochs * len(batches)
    chances = None if draw is None else [w / w.sum() for w in draw]
    fitted = Fitted(net.weights(), np.inf, 0, [], "epochs", 0.0)
    t0 = time.perf_counter()
    done, first, earlier_seconds = 0, 1, 0.0
    resume = getattr(args, "resume", None)
    if resume is not None and Path(resume).exists():
        first, done, earlier_seconds = _restore(Path(resume), args, net, optimizer, rng, fitted)
        if not args.quiet:
            print(f"resuming from {resume} after epoch {first - 1} of {args.epochs} (delete it to start over)",
                  file=sys.stderr, flush=True)
    for epoch in range(first, args.epochs + 1):
        bar = None if args.quiet else _bar(len(batches), f"epoch {epoch}")
        losses = []
        for j in rng.permutation(len(batches)):  # loop over batches of steps
            i, _ = batches[j]
            size = min(args.batch_size, len(train[i]) if draw is None else np.count_nonzero(chances[i]))
            steps = rng.choice(len(train[i]), size=size, replace=False, p=None if draw is None else chances[i])
            reflect = rng.random(len(steps)) < 0.5 if mirror else None
            # Drawn only when there is a choice, so untied runs keep their step order to the bit.
            rounds = round_counts[rng.integers(len(round_counts))] if len(round_counts) > 1 else round_counts[0]
            optimizer.learning_rate.assign(args.lr * 0.5 * (1 + np.cos(np.pi * done / total_steps)))
            batch = scaling.batch(train[i], steps, colour=colour, reflect=reflect)
            losses.append(float(train_steps[rounds](*batch)))
            if not np.isfinite(losses[-1]):
                raise TrainingDiverged(f"the training loss became {losses[-1]} in epoch {epoch}; nothing was "
                                       f"written (a smaller --lr, or --omega below 0.6 for the solver losses)")
            done += 1
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        val_loss = validate()
        fitted.history.append([epoch, round(float(np.mean(losses)), 6), round(val_loss, 6)])
        better = val_loss < fitted.loss
        if better:
            fitted.loss, fitted.epoch, fitted.weights = val_loss, epoch, net.weights()
        print(f"epoch {epoch}: train {np.mean(losses):.4f}  val {val_loss:.4f}{'  (best)' if better else ''}",
              flush=True)
        if on_epoch is not None:
            on_epoch(epoch, fitted)
        if epoch - fitted.epoch >= args.patience:
            fitted.stop_reason = f"no better validation loss for {args.patience} epochs"
        if resume is not None:
            _save_state(Path(resume), args, net, optimizer, rng, fitted, epoch, done,
                        earlier_seconds + time.perf_counter() - t0)
        if fitted.stop_reason != "epochs":
            break
    fitted.seconds = earlier_seconds + time.perf_counter() - t0
    return fitted, validate


# What a resumed run may change: where it reports, and where it keeps its state.
_RESUME_FREE = ("resume", "quiet")


def _settings(args) -> dict:
    """The arguments a resumed run must share with the run that wrote its state, as JSON reads them back."""
    return json.loads(json.dumps({k: v for k, v in sorted(vars(args).items())
                                  if k not in _RESUME_FREE and not callable(v)}, default=str))


def _save_state(path: Path, args, net, optimizer, rng: np.random.Generator, fitted: Fitted, epoch: int,
                done: int, seconds: float) -> None:
    """Everything the loop needs to go on after `epoch`, in one .npz written under a temporary name:
    the weights now and the best epoch's, Adam's variables (its step count and moments, in
    optimizer.variables' order), the step order's generator state, and the history."""
    meta = {"settings": _settings(args), "epoch": epoch, "done": done, "seconds": seconds,
            "rng": rng.bit_generator.state, "best_loss": fitted.loss, "best_epoch": fitted.epoch,
            "history": fitted.history, "stop_reason": fitted.stop_reason, "resumed_after": fitted.resumed_after}
    arrays = {f"net/{k}": v for k, v in net.weights().items()}
    arrays |= {f"best/{k}": v for k, v in fitted.weights.items()}
    arrays |= {f"adam/{i}": v.numpy() for i, v in enumerate(optimizer.variables)}
    _save_npz(path, {**arrays, "meta": np.array(json.dumps(meta))})


def _restore(path: Path, args, net, optimizer, rng: np.random.Generator, fitted: Fitted) -> tuple[int, int, float]:
    """Load what _save_state wrote into the network, the optimizer, the generator and `fitted`;
    returns (the first epoch still to run, optimizer steps taken, training seconds so far)."""
    with np.load(path, allow_pickle=False) as f:
        meta = json.loads(str(f["meta"]))
        arrays = {k: f[k] for k in f.files if k != "meta"}
    ours, theirs = _settings(args), meta["settings"]
    differ = sorted(k for k in ours.keys() | theirs.keys() if ours.get(k) != theirs.get(k))
    if differ:
        raise ResumeMismatch(f"{path} holds a run with other arguments (" +
                             ", ".join(f"--{k.replace('_', '-')} {theirs.get(k)!r} there" for k in differ) +
                             "): pass them as they were, or delete it to start over")
    for k, v in net.variables.items():
        v.assign(arrays[f"net/{k}"])
    for i, v in enumerate(optimizer.variables):  # built by _compiled_steps
        v.assign(arrays[f"adam/{i}"])
    rng.bit_generator.state = meta["rng"]
    fitted.weights = {k[len("best/"):]: v for k, v in arrays.items() if k.startswith("best/")}
    fitted.loss, fitted.epoch, fitted.history = meta["best_loss"], meta["best_epoch"], meta["history"]
    fitted.stop_reason = meta["stop_reason"]
    fitted.resumed_after = [*meta["resumed_after"], meta["epoch"]]
    # A run the patience had stopped has nothing left to train.
    first = meta["epoch"] + 1 if fitted.stop_reason == "epochs" else args.epochs + 1
    return first, meta["done"], meta["seconds"]


@dataclasses.dataclass
class _CardParts:
    """What every card of one run shares: the final model's and each checkpoint's."""

    spec: GridSpec
    args: argparse.Namespace
    command: str
    read_seconds: float
    sources: list[str]
    val_sources: list[str]
    train: list[GraphSet]
    val: list[GraphSet]

    def card(self, net, weights: dict[str, np.ndarray], onnx_bytes: bytes, *, name: str, onnx_file: str,
             parity: float, fitted: Fitted, validation: dict, **training) -> ModelCard:
        """A graph card for these weights; `training` adds to or overrides the card's training record."""
        from training.graph_model import config_to_dict, count_parameters

        args, params = self.args, count_parameters(weights)
        return ModelCard(
            name=name, kind="graph", onnx_file=onnx_file, gridspec=self.spec, fixed_grid=False,
            input_name="points", output_name="impulses", combine=args.combine, parameters=params,
            passes=getattr(args, "passes", 1),
            architecture={"config": config_to_dict(net.config), "parameters": {"total": params, "trainable": params},
                          "onnx_opset": 17, "onnx_bytes": len(onnx_bytes), "onnx_incidence": "scatter",
                          "tensorflow": net.tf.__version__},
            training={"train": [{"path": s, "steps_used": len(g), "points": len(g.targets)}
                                for s, g in zip(self.sources, self.train)],
                      "val": [{"path": s, "steps_used": len(g), "points": len(g.targets)}
                              for s, g in zip(self.val_sources, self.val)],
                      "settings": {k: getattr(args, k) for k in ("epochs", "batch_size", "lr", "patience", "width",
                                                                   "rounds", "pooled", "tangent_weight", "seed", "loss",
                                                                   "sweeps", "order", "omega", "norm", "harm_weight",
                                                                   "max_steps_per_file",
                                                                   "max_val_steps")}
                                  | ({"extra_inputs": args.extra_inputs} if getattr(args, "extra_inputs", "") else {})
                                  | ({"inputs": "scaled"} if getattr(args, "input_scale", "absolute") == "scaled" else {})
                                  | ({"layer_norm": True} if getattr(args, "layer_norm", False) else {})
                                  | ({"tied": True, "train_rounds": list(args.round_counts)}
                                     if getattr(args, "tied", False) else {})
                                  | ({"recall": True} if getattr(args, "recall", False) else {})
                                  | ({"global_state": True} if getattr(args, "global_state", False) else {})
                                  | ({"symmetric": True} if getattr(args, "symmetric", False) else {})
                                  | ({"mirror_augment": True} if getattr(args, "mirror_augment", False) else {})
                                  | ({"draw": args.draw} if getattr(args, "draw", "uniform") != "uniform" else {})
                                  | ({"self_stress_weight": args.self_stress_weight,
                                      "self_stress_iterations": args.self_stress_iterations}
                                     if args.loss == "mse-self-stress" else {}),
                      "init": None if args.init is None else str(args.init),
                      **({"teacher": Teacher.load(args.teacher).describe()}
                         if getattr(args, "teacher", None) is not None else {}),
                      **({"second_pass": Teacher.load(args.second_pass).describe()}
                         if getattr(args, "second_pass", None) is not None else {}),
                      "lr_schedule": "cosine", "epochs_run": len(fitted.history), "best_epoch": fitted.epoch,
                      "stop_reason": fitted.stop_reason, "train_seconds": round(fitted.seconds, 1),
                      **({"resumed_after_epochs": fitted.resumed_after} if fitted.resumed_after else {}),
                      "read_seconds": round(self.read_seconds, 1), "history": list(fitted.history),
                      "machine": machine.describe(), **training},
            validation={**validation, "points": int(sum(len(g.targets) for g in self.val))},
            parity_max_abs_error=parity,
            commands=(self.command,),
            trained_on=dataset.trained_on(self.sources),
        )


def _write(net, fitted: Fitted, validate, parts: _CardParts, scaling: Scaling, val: list[GraphSet]) -> ModelCard:
    """Export the best weights to args.out (ONNX, checked against TensorFlow) with their card."""
    from training.graph_model import ContactGraphNet, to_onnx

    args = parts.args
    final = ContactGraphNet(net.config, fitted.weights)
    onnx_bytes = to_onnx(final)
    parity = _parity(final, onnx_bytes, scaling.batch(val[0], np.arange(min(8, len(val[0])))))
    # The loss of a model that predicts no correction: Box2D's own warm start.
    net.variables["decode1/kernel"].assign(np.zeros_like(fitted.weights["decode1/kernel"]))
    net.variables["decode1/bias"].assign((0 - scaling.out_mean) / scaling.out_std)
    no_correction = validate()
    out = Path(args.out)
    write_bytes_atomic(out, onnx_bytes)
    _save_npz(Path(args.cache) / f"{out.stem}.weights.npz", fitted.weights)
    card = parts.card(final, fitted.weights, onnx_bytes, name=args.name or out.stem, onnx_file=out.name,
                      parity=parity, fitted=fitted,
                      validation={"epoch": fitted.epoch, "loss": fitted.loss, "loss_no_correction": no_correction})
    card.save(out.with_suffix(".json"))
    return card


def _write_checkpoint(net, epoch: int, fitted: Fitted, parts: _CardParts, scaling: Scaling,
                      val: list[GraphSet]) -> Path:
    """This epoch's network (the net's current weights) as DIR/NAME-eK.onnx and its card,
    DIR being args.checkpoints; the card's validation loss is this epoch's."""
    from training.graph_model import to_onnx

    args = parts.args
    name = f"{args.name or Path(args.out).stem}-e{epoch}"
    folder = Path(args.checkpoints)
    folder.mkdir(parents=True, exist_ok=True)
    onnx_bytes = to_onnx(net)
    parity = _parity(net, onnx_bytes, scaling.batch(val[0], np.arange(min(8, len(val[0])))))
    write_bytes_atomic(folder / f"{name}.onnx", onnx_bytes)
    card = parts.card(net, net.weights(), onnx_bytes, name=name, onnx_file=f"{name}.onnx", parity=parity,
                      fitted=fitted, validation={"epoch": epoch, "loss": fitted.history[-1][2]},
                      checkpoint_of=args.name or Path(args.out).stem, epoch=epoch)
    card.save(folder / f"{name}.json")
    return folder / f"{name}.json"


def _residual_scales(train: list[GraphSet], args) -> list[float]:
    """Per checkpoint of --sweeps: the mean squared residual (summed over normal and
    tangent) that Box2D's own warm start leaves, on up to 256 training steps (for
    solver-projected: the change a projected sweep still makes)."""
    import tensorflow as tf

    from training.graph_loss import friction_bounds, projected_changes_after, residuals_after

    gs = train[0]
    steps = np.random.default_rng(args.seed).choice(len(gs), size=min(256, len(gs)), replace=False)
    f, t, e, _ = gs.batch(steps)
    geometry, masses, inverse = gs.solver_batch(steps)
    if args.loss == "solver-projected":
        column = {n: j for j, n in enumerate(gs.inputs)}
        builtin = f[:, [column["builtin_normal"], column["builtin_tangent"]]]
        step_of = np.repeat(np.arange(len(steps), dtype=np.int32), np.diff(gs.point_offsets)[steps])
        residuals = projected_changes_after(
            tf.constant(builtin), f[:, [column["vn"], column["vt"]]], friction_bounds(tf.constant(builtin + t), step_of),
            e, geometry, masses, inverse, sweeps=args.sweeps, omega=args.omega)
    else:
        residuals = residuals_after(tf.constant(-t), e, geometry, masses, inverse, sweeps=args.sweeps,
                                    omega=args.omega)
    return [max(float(np.mean(np.sum(r.numpy() ** 2, axis=1))), 1e-12) for r in residuals]


def _parity(net, onnx_bytes: bytes, batch) -> float:
    import onnxruntime as ort

    x, e, d = batch[:3]
    feed = {"points": x, "ends": e, "dynamic": d}
    physics = {}
    if net.config.probes:
        feed.update(zip(("geometry", "masses", "inverse"), batch[4:7]))
        physics = {"physics": batch[4:7]}
    session = ort.InferenceSession(onnx_bytes, providers=["CPUExecutionProvider"])
    got = session.run(["impulses"], feed)[0]
    return float(np.abs(got - net(x, e, d, **physics).numpy()).max())


def _save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_name(f".{path.name}.{os.getpid()}.part.npz")
    try:
        np.savez(part, **arrays)
        os.replace(part, path)
    except BaseException:
        part.unlink(missing_ok=True)
        raise


def _bar(total, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", file=sys.stderr, leave=False, dynamic_ncols=True)
