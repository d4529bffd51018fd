"""Model cards: what a served ONNX model is, and how to feed it.

Every exported model `models/NAME.onnx` has a card `models/NAME.json`. The
server reads the card, never the training code, so serving transfers exactly
as training did:

    grids  = world_to_grids(bodies, contacts, card.gridspec)      # (ny, nx, Cin) raw
    x      = card.gridspec.normalize(grids, "inputs")[None]        # (1, ny, nx, Cin)
    y      = onnx(x)                                               # (1, ny, nx, Cout)
    impulses_grid = card.gridspec.denormalize(y[0], "targets")     # N s per node
    impulses = g2p(impulses_grid, contact points, card.gridspec)   # (n, 2) N s

Tensors are NHWC float32; the batch dimension is dynamic. `fixed_grid` says
whether the model only accepts `gridspec.shape` (Peak, with its dense layers)
or any grid size (Pressure, fully convolutional).

`combine` says how the model's G2P output becomes the warm start served, per
contact point, given Box2D's builtin warm start sent in the request:
    "replace"     the model's impulse (the thesis's models)
    "residual"    builtin + the model's output (a correction; models whose
                  inputs include builtin_normal/builtin_tangent), times the
                  card's `correction_scale` (default 1): a scale below 1 keeps
                  a doubtful correction from disturbing points Box2D already has
                  nearly right; corrections whose normal part is at most the
                  card's `correction_threshold` (N s, default 0) are dropped:
                  most contacts need next to none, and a model's small guesses
                  there are noise the solver must first remove
    "new-points"  the model's impulse where the point is new this step
                  (builtin exactly zero), builtin where it persists
    "persisting"  "residual" where the point persists, builtin (zero) where
                  it is new: the value of a warm start lies at persisting points
    "moving"      "residual" where one of the point's bodies moves at 0.01 m/s
                  or faster, builtin where both are at rest
                  (deepcontact.kinematics.points_at_rest): there a pile's load
                  has many arrangements the solver accepts, and a model's guess
                  is mostly wrong
Several cards may name the same ONNX file, e.g. one model served two ways.

`passes` (default 1; graph models with combine "residual" only) runs the network that
many times on a step: each later pass reads the channels at the warm start the last one
served, in place of Box2D's (which points are new to Box2D stays the request's), and adds
its correction to it. A network must be trained for that (`train-graph --second-pass`).

An alias card serves another card's model under a second name, so that users
get the best measured variant without choosing one:

    models/default.json   {"name": "default", "alias_of": "residual-new-points",
                           "why": "best measured variant, docs/results.md"}

`face` (graph models; in a full card or an alias card, which then serves its target so)
makes the server solve the step on the model's answer read as an active set: a classifier
trained on the recorded solve's labels (`train-graph --targets face`) answers each point
with about 1 N s along the normal where it presses and +-1 N s along the tangent where it
slides; the server reads that as labels (pressing above `pressing` N s, sliding at `share`
of the friction limit), solves the step's contact problem on them and moves the result by
the smallest self-stress that every friction cone admits, in at most `rounds` rounds
(deepcontact.faces.solved_on_labels). It needs each point's friction in the request
(StepRequest.point_friction). Keys: pressing (N s, default 0.5), share (default 1.0),
rounds (default 1000), label_friction (default null: each point's own friction; a number:
the sliding labels read at that friction everywhere, since the answer is a label, about
+-1 N s, not an impulse, and its reading need not follow the world's friction; the solve
uses each point's own either way), max_residual (default null: always served; a number: at a
step whose served impulses leave their labels' equations unmet by more than this share,
faces.face_residual, the labels are taken for wrong and Box2D's warm start, the request's
builtin impulses, is served instead), fallback (default null: Box2D's warm start; the name of
another card beside this one whose answer is served in its place at those steps, at steps past
max_points, at steps outside the classifier's trained_on, and where the route would miss the
request's budget_us, docs/server.md "Deadlines"; served only inside its own trained_on, Box2D's
warm start elsewhere; a card with a face of its own is another route, tried in turn, and a
chain that comes back to a card on it is refused), damping (default 0: the solve is the minimum-norm least-squares one; a
number: damped least squares, the singular values below about sqrt(damping) of the largest
damped away, solve_on_face), solver (default "gelsy": the minimum-norm solution by LAPACK's
gelsy; "dual": by faces.minimum_norm_solve, its dual by Cholesky with two rounds of
refinement, three to four times as fast at the thesis world's largest steps and nearer the
pseudo-inverse's solution than gelsy, which on about 1 % of those steps answers along a direction
that is rounding; the default card's since 2026-12-02), max_points (default null: every step solved; a number: a step
with more contact points than this is not solved, since the dense solve grows as the cube of
the points, and is served the fallback card's answer, else Box2D's warm start), retry_pressing
(default []: none; a list of thresholds in N s, only with max_residual: where the step solved on
the labels read at `pressing` misses max_residual, the labels are read again at each threshold in
turn and the first reading whose solve meets it is served, the fallback only where none does;
the step's factorizations are shared, so a retry costs its solve and admission rounds), close
(default null: off; a speed in m/s: the points labelled open that the solve on the labels leaves
closing faster than that are labelled pressing and the step solved again before the admission,
faces.solved_on_labels), relax (default 1: the admission's rounds plain ADMM; a number between 0
and 2: their over-relaxation, deepcontact/admission_kernels.h, above 1 fewer rounds to the same
answer where the rounds crawl along the cones), rho (default 100: the admission's ADMM penalty,
admission.nearest_admissible; larger, the rounds' pull toward the solve's own answer weaker and
the bodies' motion reached sooner, which a served step cut at `rounds` rounds ends nearer),
against_builtin (default false; true: the route's
answer is served only where one projected Jacobi step from it would change the impulses less than
one from Box2D's warm start, kinematics.jacobi_change, and Box2D's elsewhere: a check that needs
no trust in the labels, for a route on worlds its classifier may not know), check_sweeps
(default null: against_builtin's comparison is that one Jacobi step; a whole number N >= 1: the
largest change the solver's N-th sweep of sequential impulses would make from each start,
faces.sweep_changes, nearer to how the solver itself stops), check_stop (default false; true,
with check_sweeps N and a client that declares its stopping rule, World.solver_tolerance: the
sweeps each start takes to that rule, up to N, faces.sweeps_to_stop, the route's answer served
where it stops sooner, and by the last sweep's changes where both stop at the same sweep or neither
by sweep N; a client that does not declare it is checked by the changes as without), by_island
(default false; true, with check_stop: the check counts each island of the step, as Box2D's solver
forms and stops them, on its own, faces.island_sweeps_to_stop, and serves each island the start
that stops it sooner, the route's answer on some and Box2D's on the others), rescale (default
false; true: a step of larger or smaller bodies, denser, or with a larger or smaller gravity times
time step than the classifier's `trained_on` is labelled scaled into it, deepcontact.envelope.Envelope.rescaled, and
solved in its own units; the reply's familiar verdict stays the unscaled step's), carry (default
false; true: along a stream, each point's admission begins where the same point's ended on the
step before, deepcontact.admission.AdmissionCarry, so that the rounds cut at `rounds` go on
across steps; a step alone, or a point new to the stream, begins cold as before),
extrapolate_jointed (default false: at points on jointed bodies, which no model speaks for,
server.joints, Box2D's start as it is; true: along a stream, that start extrapolated in time
from the point's last two steps, deepcontact.temporal.ImpulseHistory), slide_in_bodies (default
true: the compiled route's solve tries the bodies' space where points slide too, and answers there
where every body they push is held, deepcontact.faces.route_compiled; false: such a step goes to
the dual at once, for a card whose world is a pile of discs, where sliding points leave turnings
free and the bodies' space declines nearly every such step after its first factor), min_rounds
(default null: with a deadline the route is taken where it is expected to end in all its `rounds`;
a whole number 1 to `rounds`: where it is expected to end in min_rounds of them, its admission then
running rounds up to `rounds` while the check after them would still end by the deadline, so a
large step gets fewer rounds rather than no route), revolute_joints (default false; true: where
every joint of a request is a revolute, rigid weld or prismatic one and it sends them (StepRequest.joint_revolute, their limits and motors in joint_limits)
with its stopping rule, the route asks its classifier about the step with each joint as two points
and serves, of five starts, the one that stops soonest on the server's copy of the step with the
joints swept as Box2D sweeps them, the joints' start on the reply where it is the route's,
server.revolute; read from the last face route along a card's fallbacks), held_labels (default
false; true: along a stream, the classifier's labels are held by contact point, and a step that
the route would not end by its deadline with its classifier, but would without it, and whose every
point has labels held from the last three steps, is solved on those, the classifier labelling it
after the reply on the spare core for the steps after it, server.held_labels), check_work
(default null; a whole number, with check_sweeps: the check plays no more than check_work /
points sweeps from each start on a step, at least one, so that a large step's check costs no
more point-sweeps than a smaller one's), held_from_builtin (default false; true, with
held_labels: a point with no labels held, new on the step, is read from Box2D's start, as its face
written as labels (deepcontact.faces.face_labels), so that every step the route would not end in
time with its classifier, but would without it, is solved on labels), repairs (default 0; a
whole number 1 to 8, with by_island: the route's answer is repaired up to that many times in
turn, each repair one step of an active-set method read off the answer before it
(deepcontact.faces.repair_face, each point's bounce held) and the step solved and admitted again
on the repaired labels, none begun after the deadline, and the check serves each island the
start that stops it soonest among Box2D's, the route's answer and its repairs), repair_rounds
(default null: each repair admitted in the card's `rounds`; a whole number 1 to `rounds`, with
repairs: each repair's admission ends after that many, a repair's labels being close to the
answer's it mends).

`ModelCard.load` resolves it to the card it names (beside it), renamed; an
alias of an alias is refused, so the chain is one step and cannot loop.

`trained_on` (optional) is what the model's training data held (deepcontact.envelope.Envelope:
shapes, radius, density, friction, gravity, dt, joints, kinematic bodies); the server tells the
client, with each reply, whether the step lies inside it. A card without it is unfamiliar with
every world. train-graph writes it from its training files' scenes.

`measured` (optional; in a full card or an alias card) is what the model, served as the card
says, was measured to need on the worlds of its trained_on, without the guard: {"ratio": mean
iterations over Builtin's, "interval": [low, high] its 95 % bootstrap interval over seeds,
"command": the command that measured it}, on choosing seeds. The server calls a step familiar
(and the client's guard trusts the model there from the first step) only where the step lies
inside trained_on and the whole interval lies below 1: a model trained on a world but not
measured to win there (the thesis's Pressure CNN) is held to Box2D's start like any other.

`mirror` (graph models; in a full card or an alias card, which then serves its target so;
default false) serves the network with its mirror image: it answers the step and the step
reflected left to right (x -> -x, each channel times its sign under the reflection,
deepcontact.channels Channel.mirror), and the mean of its answer and the reflected answer
reflected back is served, as `python -m training.ensemble --mirror` builds into one ONNX graph.
The worlds are symmetric under the reflection and the networks are not built to be; the mean
errs less than either half. The server runs the two halves as two calls, the reflected one on
a spare core where it has one (server.mirror_image.MirroredGraphPredictor).

`step_gate` (graph models with combine "residual"; in a full card or an alias card, which
then serves its target gated) holds a per-step gate (deepcontact.step_gate.StepGate.to_dict):
at a step where it predicts that the model's warm start loses to Box2D's, the server serves
Box2D's, the request's builtin impulses unchanged. `deepcontact lab step-gate --save-card
NAME` fits one and writes such an alias.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import os
from pathlib import Path
from typing import Any

from deepcontact.envelope import Envelope
from deepcontact.gridspec import GridSpec
from deepcontact.io import write_json_atomic
from deepcontact.faces import SOLVERS
from deepcontact.step_gate import StepGate

CARD_VERSION = 1
COMBINE = ("replace", "residual", "new-points", "persisting", "moving")
ALIAS_KEYS = frozenset({"name", "alias_of", "why", "step_gate", "face", "mirror", "description", "measured"})
#: What an alias card may set for the card it names (the rest is the target's).
ALIAS_OVERRIDES = ("step_gate", "face", "mirror", "description", "measured")
#: A card's `face` settings, and their defaults (see above).
FACE_DEFAULTS = {"pressing": 0.5, "share": 1.0, "rounds": 1000, "label_friction": None, "max_residual": None,
                 "fallback": None, "damping": 0.0, "max_points": None, "solver": "gelsy", "retry_pressing": [], "close": None,
                 "relax": 1.0, "rho": 100.0, "against_builtin": False, "rescale": False,
                 "carry": False, "check_sweeps": None, "extrapolate_jointed": False, "check_stop": False,
                 "slide_in_bodies": True, "min_rounds": None, "revolute_joints": False, "by_island": False,
                 "restitution": True, "held_labels": False, "check_work": None,
                 "held_from_builtin": False, "repairs": 0, "repair_rounds": None}


class ModelCardError(ValueError):
    """A card that is missing, malformed or does not match its model."""


#: Up to this many known names are listed whole; past it (models/ ships well over a hundred
#: cards) only the closest ones, so that the message stays readable on one screen.
LIST_ALL_UP_TO = 12


def unknown_model(name: str, known: list[str] | tuple[str, ...] | set[str]) -> str:
    """The end of an error message for a model name that is not among `known`:
    "no model 'NAME'; ..." followed by every known name when there are few, else the
    closest few (difflib) and how many there are."""
    known = sorted(known)
    if not known:
        return f"no model {name!r}; there is none"
    if len(known) <= LIST_ALL_UP_TO:
        return f"no model {name!r}; there are {', '.join(known)}"
    close = difflib.get_close_matches(name, known, n=5, cutoff=0.5)
    hint = f"the closest: {', '.join(close)}" if close else f"none is close; e.g. {', '.join(known[:3])}, ..."
    return f"no model {name!r} among {len(known)} ({hint})"


@dataclasses.dataclass(frozen=True)
class ModelCard:
    name: str
    kind: str  # "pressure", "peak", ...
    onnx_file: str  # file name beside the card
    gridspec: GridSpec
    fixed_grid: bool
    input_name: str = "grids"
    output_name: str = "impulses"
    combine: str = "replace"  # "replace", "residual", "new-points", "persisting" or "moving" (see above)
    correction_scale: float = 1.0  # "residual", "persisting", "moving": builtin + correction_scale x the model's correction
    correction_threshold: float = 0.0  # "residual", "persisting", "moving": drop corrections whose normal part is at most this (N s)
    passes: int = 1  # graph "residual" models: the network run this many times, each from the last one's warm start
    step_gate: dict | None = None  # graph "residual" models: Box2D's warm start served at the steps it picks (see above)
    face: dict | None = None  # graph models: the step solved on the answer read as labels (see above)
    mirror: bool = False  # graph models: served with the network's mirror image (see above)
    parameters: int = 0
    architecture: dict = dataclasses.field(default_factory=dict)
    training: dict = dataclasses.field(default_factory=dict)  # scene, seeds, epochs, ...
    validation: dict = dataclasses.field(default_factory=dict)  # losses
    parity_max_abs_error: float | None = None  # TF vs ONNX Runtime on random input
    commands: tuple[str, ...] = ()  # the commands that made the model
    description: str = ""  # what the model is, in one line: ListModels returns it, `deepcontact serve` logs it
    trained_on: dict | None = None  # what its training data held (deepcontact.envelope.Envelope.to_dict)
    measured: dict | None = None  # its iterations over Builtin's on those worlds: ratio, interval, command
    version: int = CARD_VERSION

    @property
    def envelope(self) -> Envelope | None:
        """The card's trained_on as an Envelope (None: the card records none)."""
        return None if self.trained_on is None else Envelope.from_dict(self.trained_on)

    @property
    def wins_where_trained(self) -> bool:
        """Whether the card records a measured gain over Box2D's start on its training worlds
        (`measured`'s whole interval below 1)."""
        return self.measured is not None and self.measured["interval"][1] < 1.0

    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["gridspec"] = self.gridspec.to_dict()
        d["commands"] = list(self.commands)
        return json.loads(json.dumps(d))  # plain JSON types only

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ModelCard":
        if not isinstance(d, dict):
            raise ModelCardError(f"a model card is a JSON object, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ModelCardError(f"unknown model card keys {sorted(unknown)}")
        missing = {"name", "kind", "onnx_file", "gridspec", "fixed_grid"} - set(d)
        if missing:
            raise ModelCardError(f"model card lacks {sorted(missing)}")
        if d.get("version", CARD_VERSION) != CARD_VERSION:
            raise ModelCardError(f"model card version {d['version']!r}, this code reads {CARD_VERSION}")
        d = dict(d)
        try:
            d["gridspec"] = GridSpec.from_dict(d["gridspec"])
        except ValueError as exc:
            raise ModelCardError(f"model card gridspec: {exc}") from None
        d["commands"] = tuple(d.get("commands", ()))
        passes = d.get("passes", 1)
        if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
            raise ModelCardError(f"model card passes {passes!r}: a whole number, 1 or more")
        if passes > 1 and (d["kind"] != "graph" or d.get("combine", "replace") != "residual"):
            raise ModelCardError(f"model card passes {passes}: only a graph model with combine \"residual\" "
                                 f"can start a pass from its last one's warm start")
        if d.get("step_gate") is not None:
            if d["kind"] != "graph" or d.get("combine", "replace") != "residual":
                raise ModelCardError("model card step_gate: only a graph model with combine \"residual\" is gated")
            try:
                StepGate.from_dict(d["step_gate"])
            except ValueError as exc:
                raise ModelCardError(f"model card step_gate: {exc}") from None
        if d.get("face") is not None:
            d["face"] = _face_settings(d["face"], d["kind"])
        mirror = d.get("mirror", False)
        if not isinstance(mirror, bool):
            raise ModelCardError(f"model card mirror {mirror!r}: true or false")
        if mirror and d["kind"] != "graph":
            raise ModelCardError("model card mirror: only a graph model is served with its mirror image")
        if d.get("trained_on") is not None:
            try:
                d["trained_on"] = Envelope.from_dict(d["trained_on"]).to_dict()
            except ValueError as exc:
                raise ModelCardError(f"model card {exc}") from None
        if d.get("measured") is not None:
            d["measured"] = _measured(d["measured"])
        if not isinstance(d.get("description", ""), str) or "\n" in d.get("description", ""):
            raise ModelCardError("model card description: one line of text")
        if d.get("combine", "replace") not in COMBINE:
            raise ModelCardError(f"model card combine {d['combine']!r}: use one of {', '.join(COMBINE)}")
        return cls(**d)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the card as JSON (temporary name, then rename)."""
        return write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ModelCard":
        """The card at path; an alias card resolved to the card it names, renamed."""
        path = Path(path)
        data = _read_card(path)
        if isinstance(data, dict) and "alias_of" in data:
            unknown = set(data) - ALIAS_KEYS
            if unknown or not isinstance(data.get("name"), str) or not isinstance(data["alias_of"], str):
                raise ModelCardError(f"{path}: an alias card holds a name and alias_of (strings) and "
                                     f"optionally why, description, step_gate, face, mirror and measured; got keys "
                                     f"{sorted(data)}")
            target_path = path.with_name(f"{data['alias_of']}.json")
            target = _read_card(target_path)
            if isinstance(target, dict) and "alias_of" in target:
                raise ModelCardError(f"{path}: alias of {target_path.name}, itself an alias; "
                                     f"name the card it points at ({target['alias_of']!r})")
            if isinstance(target, dict):
                target = {**target, **{k: data[k] for k in ALIAS_OVERRIDES if k in data}}
            try:
                card = cls.from_dict(target)
            except ModelCardError as exc:
                raise ModelCardError(f"{target_path} (alias target of {path.name}): {exc}") from None
            return dataclasses.replace(card, name=data["name"])
        try:
            return cls.from_dict(data)
        except ModelCardError as exc:  # a folder of cards: say which one
            raise ModelCardError(f"{path}: {exc}") from None

    @staticmethod
    def alias_target(path: str | os.PathLike) -> str | None:
        """The name an alias card at path points at; None for a full card."""
        data = _read_card(Path(path))
        return data.get("alias_of") if isinstance(data, dict) else None

    def onnx_path(self, card_path: str | os.PathLike) -> Path:
        return Path(card_path).with_name(self.onnx_file)


def _face_settings(face: Any, kind: str) -> dict:
    """A card's `face` with its defaults filled; ModelCardError for anything else."""
    if kind != "graph":
        raise ModelCardError("model card face: only a graph model's answer is read as labels")
    if not isinstance(face, dict) or set(face) - set(FACE_DEFAULTS):
        raise ModelCardError(f"model card face: an object with keys among {sorted(FACE_DEFAULTS)}, got {face!r}")
    out = {**FACE_DEFAULTS, **face}
    optional = ("label_friction", "max_residual", "close")
    sweeps, fewest, work = out["check_sweeps"], out["min_rounds"], out["check_work"]
    mending = out["repair_rounds"]
    numbers = all(isinstance(out[k], (int, float)) and not isinstance(out[k], bool)
                  for k in out if k not in ("fallback", "solver", "retry_pressing", "against_builtin", "rescale", "carry",
                                           "extrapolate_jointed", "check_stop", "slide_in_bodies", "revolute_joints",
                                           "by_island", "restitution", "held_labels", "held_from_builtin",
                                           "repairs")
                  and not (k in optional + ("max_points", "check_sweeps", "min_rounds", "check_work", "repair_rounds")
                           and out[k] is None))
    retries = out["retry_pressing"]
    retries_ok = isinstance(retries, list) and all(isinstance(r, (int, float)) and not isinstance(r, bool) and r >= 0
                                                   for r in retries) and (not retries or out["max_residual"] is not None)
    fallback, most = out["fallback"], out["max_points"]
    if not numbers or not out["pressing"] >= 0 or not out["share"] > 0 or not isinstance(out["rounds"], int) \
            or out["rounds"] < 1 or any(out[k] is not None and not out[k] > 0 for k in optional) \
            or not out["damping"] >= 0 or not (fallback is None or isinstance(fallback, str) and fallback) \
            or not (most is None or isinstance(most, int) and most >= 1) or out["solver"] not in SOLVERS \
            or not retries_ok or not 0 < out["relax"] < 2 or not out["rho"] > 0 \
            or not isinstance(out["against_builtin"], bool) \
            or not isinstance(out["rescale"], bool) or not isinstance(out["carry"], bool) \
            or not isinstance(out["extrapolate_jointed"], bool) or not isinstance(out["check_stop"], bool) \
            or not isinstance(out["slide_in_bodies"], bool) or not isinstance(out["revolute_joints"], bool) \
            or not isinstance(out["by_island"], bool) or (out["by_island"] and not out["check_stop"]) \
            or not isinstance(out["restitution"], bool) or not isinstance(out["held_labels"], bool) \
            or not isinstance(out["held_from_builtin"], bool) or (out["held_from_builtin"] and not out["held_labels"]) \
            or not (isinstance(out["repairs"], int) and not isinstance(out["repairs"], bool)
                    and 0 <= out["repairs"] <= 8) or (out["repairs"] and not out["by_island"]) \
            or not (sweeps is None or isinstance(sweeps, int) and 1 <= sweeps <= 1000) \
            or (out["check_stop"] and sweeps is None) \
            or not (work is None or isinstance(work, int) and work >= 1 and sweeps is not None) \
            or not (fewest is None or isinstance(fewest, int) and 1 <= fewest <= out["rounds"]) \
            or not (mending is None or isinstance(mending, int) and 1 <= mending <= out["rounds"] and out["repairs"]):
        raise ModelCardError(f"model card face: pressing >= 0 (N s), share > 0, rounds a whole number >= 1, relax "
                             f"between 0 and 2, rho > 0, "
                             f"label_friction, max_residual and close null or > 0, damping >= 0, max_points null or a "
                             f"whole number >= 1, fallback null or a card's name, solver one of {SOLVERS}, "
                             f"retry_pressing a list of numbers >= 0 (N s) and only with max_residual, against_builtin, "
                             f"rescale, carry, extrapolate_jointed, slide_in_bodies, revolute_joints, restitution and held_labels true or false, "
                             f"check_sweeps null or a "
                             f"whole number 1-1000, "
                             f"check_stop true or false and only with check_sweeps, check_work null or a whole "
                             f"number >= 1 and only with check_sweeps, by_island true or false and only "
                             f"with check_stop, min_rounds null or a whole "
                             f"number 1 to rounds, held_from_builtin true or false and only with held_labels, "
                             f"repairs a whole number 0-8 and above 0 only with by_island, repair_rounds null or a "
                             f"whole number 1 to rounds and only with repairs, "
                             f"got {face!r}")
    return {"pressing": float(out["pressing"]), "share": float(out["share"]), "rounds": out["rounds"],
            **{k: None if out[k] is None else float(out[k]) for k in optional},
            "fallback": fallback, "damping": float(out["damping"]), "max_points": most, "solver": out["solver"],
            "retry_pressing": [float(r) for r in retries], "relax": float(out["relax"]), "rho": float(out["rho"]),
            "against_builtin": out["against_builtin"], "rescale": out["rescale"], "carry": out["carry"],
            "check_sweeps": sweeps, "extrapolate_jointed": out["extrapolate_jointed"], "check_stop": out["check_stop"],
            "slide_in_bodies": out["slide_in_bodies"], "min_rounds": fewest, "revolute_joints": out["revolute_joints"],
            "by_island": out["by_island"], "restitution": out["restitution"], "held_labels": out["held_labels"],
            "check_work": work, "held_from_builtin": out["held_from_builtin"], "repairs": out["repairs"],
            "repair_rounds": mending}


def _measured(m: Any) -> dict:
    """A card's `measured`, checked; ModelCardError for anything else."""
    number = lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0  # noqa: E731
    if not (isinstance(m, dict) and set(m) == {"ratio", "interval", "command"} and number(m["ratio"])
            and isinstance(m["interval"], list) and len(m["interval"]) == 2 and all(map(number, m["interval"]))
            and m["interval"][0] <= m["ratio"] <= m["interval"][1] and isinstance(m["command"], str)):
        raise ModelCardError(f"model card measured: {{\"ratio\": r, \"interval\": [low, high], \"command\": "
                             f"\"...\"}} with 0 < low <= r <= high, got {m!r}")
    return {"ratio": float(m["ratio"]), "interval": [float(x) for x in m["interval"]], "command": m["command"]}


def _read_card(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ModelCardError(f"{path}: no model card") from None
    except json.JSONDecodeError as exc:
        raise ModelCardError(f"{path}: not JSON ({exc})") from None
