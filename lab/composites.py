"""Warm starts over warm starts: each step the engine solves the step from Box2D's warm start
and from each candidate's (trial solves, the world unchanged), and one of them is served.
The stepping loop (simclient.stepping) asks every candidate, then calls Pick.pick(); Pick is a
simclient.provider.Composite. Each mode below is registered with simclient.warmstarts as a
composite prefix (MODE:W1+W2+..., and solved@P:W) when `lab` is imported.

    provider = make_provider("price:server:default+oracle:near")   # simclient.warmstarts.make_provider

    pick:W1+W2+...  each step, the engine solves the step from Box2D's warm start and
                 from each of W1, W2, ... (any warm starts, e.g. server:default;
                 trial solves, the world unchanged) and keeps the one that takes the
                 fewest iterations (builtin on a tie): what a perfect per-step choice
                 among them is worth. A solve per candidate; not one a server could serve
    shadow:W1+W2+...  serves W1 every step, as W1 alone would, and trial-solves builtin
                 and the others beside it: each against builtin on W1's own trajectory
    mean:W1+W2+...  serves the mean of W1, W2, ... and trial-solves builtin, each of them
                 and the mean on the same states: does averaging two kinds of guess pay?
    price:W1+W2+...  serves builtin, so its steps are Builtin's own, and trial-solves
                 W1, W2, ... beside it: every model priced on one set of states, the same
                 in every run, so two models (or two checkpoints) measured apart are
                 compared step by step, with no trajectory between them
    split:W      serves W, as W alone would, and trial-solves builtin, W, and the two
                 parts of W's correction (W - builtin) each alone on Box2D's warm start:
                 the part that moves the bodies and the self-stress that moves none
                 (oracle:body-space, oracle:self-stress): which part of a model's
                 correction pays
    boost:W      serves W, as W alone would, and trial-solves builtin, W, and W's
                 correction with its self-stress part scaled by 0.5, 1.5, 2 and 3 (the part
                 that moves the bodies kept): is a model's self-stress right in direction
                 and short in size?
    admit:W      serves W, as W alone would, and trial-solves builtin, W, and forms of
                 it made admissible (deepcontact.kinematics.nearest_admissible): W
                 moved by the smallest self-stress that brings every point inside its
                 friction cone; builtin plus W's body-space part moved the same way
                 (W's motion, the self-stress chosen by the limits alone); and that with
                 the points W's motion pulls apart held at 0 (oracle:near-admissible-separating's rule);
                 and builtin plus W's motion at the moving bodies only, Box2D's at the others,
                 admitted (oracle:near-admissible-moving's split), and the same not admitted
                 (normal impulses clamped at 0 only): does the admission pay, or the split?
    motion:W     serves W, as W alone would, and trial-solves builtin, W, and builtin plus W's
                 motion (its body-space correction) times 1, 1.25 and 1.5, admitted, then the same
                 for W's motion at the moving bodies only (Box2D's at the others): the exact
                 motion admitted pays more a quarter too large than a quarter too small
                 (oracle:near-admissible-scaled@S), so is a model's motion short in size?
    graft:W1+W2  serves W1, as W1 alone would, and trial-solves builtin, W1, W2, and W1 with W2's
                 motion at the moving bodies (W1 plus the least-norm change that moves them as W2
                 does and no other body), admitted and not: one model's self-stress and resting
                 bodies with another's moving bodies
    shrink:W+E   serves builtin, so its steps are Builtin's own (as price:), and trial-solves
                 W, E, and E plus W's error against E (W - E) times 1/2, 1/4 and 3/4, then
                 its two parts each halved alone: the part that moves the bodies and the
                 self-stress. With E = oracle:near: how much better must W be, in its own
                 error's shape, and in which part of it?
    gate:W+E     serves builtin (as price:) and trial-solves W, E, and at each point W or
                 Box2D's warm start, whichever lies nearer E there (a hard gate), then
                 Box2D's warm start moved toward W by the share of the way that comes
                 nearest E at each point (a soft gate, 0 to 1), and the same share taken
                 for normal and tangent apart. With E = oracle:near: the most any gate
                 between a model and Box2D's warm start, learned per point, could be worth
    face:W+E     serves builtin (as price:) and trial-solves W, E, and the step solved on E's face
                 (its active set: which points let go, stick, or slide which way;
                 deepcontact.kinematics.solve_on_face), on E's face with 1, 3 or 10 of its
                 labels swapped for W's where they differ, with W's labels where either says
                 a point is open and then where both say it presses (W's two kinds of error),
                 on W's face and on Box2D's warm start's, and on W's face read as a classifier's
                 labels (train-graph --targets face: pressing above 0.5 N s, sliding at the
                 limit), each admitted with that face's open points held at 0; the last two
                 also repaired once and twice (an active-set method's steps,
                 deepcontact.kinematics.repair_face); notes per step
                 how many labels differ, and how. With E =
                 oracle:near: the face alone fixes the bodies' motion; how right must a learned
                 face be?
    solved:W     serves the step solved on W's face read as a classifier's labels (as face:
                 does, FACE_LABELS), admitted with its open points held at 0: the face route
                 closed loop, on its own trajectory. W is a classifier (train-graph --targets
                 face); the solve runs here, in the client (deepcontact.kinematics.solved_on_labels,
                 the admission in full; a card with `face` serves the same from the server, e.g.
                 server:face). Trial-solves builtin, W and the solved start beside it; where
                 W falls back it serves Box2D's warm start. solved@P:W reads W's labels pressing
                 above P N s (default FACE_LABELS' 0.5)
    solved-forms:W  serves as solved:W does and also prices, on the same states, the same
                 motion with Box2D's warm start's self-stress (admitted from there, not from
                 the least-norm impulses), the admission cut at SOLVED_ROUNDS of its rounds
                 (what a server could afford), and W's labels read with the pressing
                 threshold at each of SOLVED_PRESSING (more solves a step: slower)
    jittered@S:W  serves W's answer plus Gaussian noise of S N s at the points that persist
                 (normal impulses clamped at 0; seeded, so the same noise every run), and
                 trial-solves builtin and W beside it: one more draw of W's closed loop, another
                 trajectory of the same warm start (as jitter@S is of Box2D's; lab spread).
                 jittered:W is jittered@1e-7:W
    feedback:W   serves W, as W alone would, and trial-solves builtin, W, and W less G times
                 its own error on the previous step at each point that persists (what W served
                 there minus where the solve ended, matched by key), for G in 0.25, 0.5 and 1:
                 are a model's errors the same from one step to the next, so that a server that
                 remembered them could take them off? (G = 1 is Box2D's warm start plus the
                 model's change since the previous step)
"""

from __future__ import annotations

import numpy as np

from lab.oracles import SEPARATING_SPEED
from simclient.provider import Composite, Provider, as_warm_start, body_friction, persisting_rows, point_friction
from simclient.warmstarts import composite_parts, make_provider, register_prefix


class Pick(Composite):
    """An oracle over warm starts: each step, the engine solves the step from
    Box2D's warm start and from each candidate's (trial solves, the world
    unchanged) and keeps the one that takes the fewest iterations (builtin on
    a tie). The stepping loop asks every candidate, then calls pick()."""

    MODES = ("pick", "shadow", "mean", "price", "split", "boost", "admit", "motion", "graft", "feedback", "shrink",
             "gate", "face", "solved", "solved-forms", "jittered")
    #: shrink:W+E: the factors W's whole error is priced at.
    SHRINKS = (0.75, 0.5, 0.25)
    #: boost:W: the factors its self-stress part is priced at.
    BOOSTS = (0.5, 1.5, 2.0, 3.0)
    #: motion:W: the factors its motion is admitted at.
    MOTION_SCALES = (1.0, 1.25, 1.5)
    #: feedback:W: the shares of its previous step's error it is priced less.
    FEEDBACKS = (0.25, 0.5, 1.0)
    #: face:W+E: how many of the reference's labels are swapped for W's where they differ.
    FACE_SWAPS = (1, 3, 10)
    #: face:W+E: W's face read again as a classifier's labels written as impulses (train-graph
    #: --targets face): pressing above this normal impulse (N s), sliding at this share of the limit.
    FACE_LABELS = (0.5, 1.0)
    #: face:W+E: builtin's face and W's read as labels, each also repaired this many times in
    #: turn (deepcontact.kinematics.repair_face: an active-set method's steps), each repair priced.
    FACE_REPAIRS = 2
    #: solved:W: the other pressing thresholds (N s) W's labels are priced at.
    SOLVED_PRESSING = (0.25, 0.75)
    #: solved-forms:W: the admission's rounds in its cut form (nearest_admissible's iterations).
    SOLVED_ROUNDS = 50
    #: jittered:W: the noise added to W's answer at persisting points, N s (jittered@S:W sets it).
    NOISE = 1e-7

    @classmethod
    def names_one(cls, name: str) -> bool:
        """Whether a warm-start name is one of these composites (solved@P:W included)."""
        head = name.split(":", 1)[0]
        mode = head.split("@", 1)[0]
        return ":" in name and mode in cls.MODES and (head == mode or mode.startswith("solved") or mode == "jittered")

    def __init__(self, candidates: list[Provider], mode: str = "pick", pressing: float | None = None,
                 noise: float | None = None):
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {self.MODES}, got {mode!r}")
        if pressing is not None:  # solved@P:W, W's labels read pressing above P N s
            if not mode.startswith("solved") or not pressing >= 0:
                raise ValueError(f"a pressing threshold goes with solved: only, and is >= 0 N s, got {pressing!r}")
            self.FACE_LABELS = (pressing, self.FACE_LABELS[1])
        if noise is not None:  # jittered@S:W, S N s of noise on W's answer
            if mode != "jittered" or not (np.isfinite(noise) and noise > 0):
                raise ValueError(f"a noise size goes with jittered: only, and is > 0 N s, got {noise!r}")
            self.NOISE = noise
        self._rng = np.random.default_rng(0)  # jittered: a fresh provider per world, the same noise every run
        super().__init__(candidates)
        # pick: serve the cheapest; shadow: serve the first, price the others beside it;
        # mean: serve the candidates' mean, price it and each of them on the same state;
        # price: serve builtin, price the candidates on its states (the same states for every
        # model and every run: a paired, trajectory-free comparison of any two models);
        # split: serve the one candidate, price it and the two parts of its correction;
        # boost: serve the one candidate, price it with its self-stress part scaled;
        # admit: serve the one candidate, price it and its admissible forms;
        # motion: serve the one candidate, price its motion scaled and admitted;
        # graft: serve the first, price it with the second's moving bodies' motion;
        # feedback: serve the one candidate, price it less shares of its last step's error
        # shrink: serve builtin, price the first candidate's error against the second scaled, and its parts
        # gate: serve builtin, price the first candidate gated per point against builtin, judged by the second
        # solved: serve the step solved on the one candidate's labels, price it and the candidate
        if mode in ("split", "boost", "admit", "motion", "feedback", "solved", "solved-forms", "jittered") \
                and len(candidates) != 1:
            raise ValueError(f"{mode}: takes one warm start, e.g. {mode}:server:default, got {len(candidates)}")
        if mode in ("shrink", "gate", "face") and len(candidates) != 2:
            raise ValueError(f"{mode}: takes a warm start and its reference, e.g. {mode}:server:default+oracle:near, "
                             f"got {len(candidates)}")
        if mode == "graft" and len(candidates) != 2:
            raise ValueError(f"graft: takes two warm starts, e.g. graft:server:default+server:graph-mse-1-799-moving-rel, "
                             f"got {len(candidates)}")
        self.mode = mode
        for i, c in enumerate(candidates):
            if hasattr(c, "reseed"):  # jitter@S
                c.reseed(i)  # two jitters in one pick draw different noise
        at = "" if pressing is None and noise is None else f"@{pressing if noise is None else noise:g}"
        self.name = f"{mode}{at}:" + "+".join(c.name for c in candidates)
        # trials: per step with contacts, builtin's, then each candidate's iterations; reach: the same
        # steps, each one's sweeps to Builtin's accuracy (sweeps_to_builtin); notes: what note_labels names
        # feedback: the candidate's answer this step, (keys (P,), impulses (P, 2) N s), until observe() scores it,
        # then its error at the previous step's points, sorted by key
        self._answer: tuple[np.ndarray, np.ndarray] | None = None
        self._error_keys, self._error = np.zeros(0, np.uint64), np.zeros((0, 2))

    @property
    def labels(self) -> list[str]:
        """What each entry of a trials row priced: builtin, the candidates (and their mean)."""
        first = self.candidates[0].name
        extra = {"mean": ["mean"], "split": [f"{first} body-space", f"{first} self-stress"],
                 "boost": [f"{first} self-stress x{k:g}" for k in self.BOOSTS],
                 "admit": [f"{first} admissible", f"{first} body-space admissible",
                           f"{first} body-space admissible, separating open",
                           f"{first} moving bodies' motion admissible", f"{first} moving bodies' motion"],
                 "motion": [f"{first} motion x{k:g} admissible" for k in self.MOTION_SCALES]
                 + [f"{first} moving bodies' motion x{k:g} admissible" for k in self.MOTION_SCALES],
                 "graft": [f"{first} with {self.candidates[-1].name}'s moving bodies' motion admissible",
                           f"{first} with {self.candidates[-1].name}'s moving bodies' motion"],
                 "feedback": [f"{first} less {g:g} x its last error" for g in self.FEEDBACKS],
                 "jittered": [f"{first} plus noise of {self.NOISE:g} N s"],
                 "shrink": [f"{first} error x{k:g}" for k in self.SHRINKS]
                 + [f"{first} error's body-space part x0.5", f"{first} error's self-stress x0.5"],
                 "gate": [f"{first} or builtin, the nearer at each point", f"{first} gated at each point",
                          f"{first} gated at each point, normal and tangent apart"],
                 "face": [f"solved on {self.candidates[-1].name}'s face"]
                 + [f"solved on {self.candidates[-1].name}'s face, {k} of {first}'s labels" for k in self.FACE_SWAPS]
                 + [f"solved on {self.candidates[-1].name}'s face, {first}'s labels where either says open",
                    f"solved on {self.candidates[-1].name}'s face, {first}'s labels where both press",
                    f"solved on {first}'s face", "solved on builtin's face",
                    f"solved on {first}'s face read as labels"]
                 + [f"solved on {who}'s face{how}, repaired {k}x" for who, how in (("builtin", ""), (first, " read as labels"))
                    for k in range(1, self.FACE_REPAIRS + 1)],
                 "solved": [f"solved on {first}'s face read as labels"],
                 "solved-forms": [f"solved on {first}'s face read as labels",
                                  f"solved on {first}'s face read as labels, Box2D's self-stress",
                                  f"solved on {first}'s face read as labels, admitted in {self.SOLVED_ROUNDS} rounds"]
                 + [f"solved on {first}'s face read as labels pressing above {k:g} N s"
                    for k in self.SOLVED_PRESSING]}.get(self.mode, [])
        return ["builtin", *(c.name for c in self.candidates)] + extra

    @property
    def note_labels(self) -> list[str]:
        """What each entry of a notes row counts (face: the step's points and where faces differ)."""
        if self.mode != "face":
            return []
        from deepcontact.faces import FACE_ERRORS

        guess, reference = (c.name for c in self.candidates)
        return ["points"] + [f"points where {who}'s face {what} (against {reference}'s)" for who in (guess, "builtin")
                             for what in ("differs", *FACE_ERRORS)]

    @property
    def serves(self) -> str:
        """Whose start the steps were served (the trajectory the trials are on), as a table says it."""
        if self.mode in ("price", "shrink", "gate", "face"):
            return "Builtin's"
        if self.mode == "mean":
            return "the mean's"
        if self.mode.startswith("solved"):
            return "the solved start's"
        return "the picked" if self.mode == "pick" else "the first candidate's"

    def prepare(self, engine) -> None:
        self._friction = body_friction(engine)
        super().prepare(engine)

    def observe(self, points_after_solve):
        super().observe(points_after_solve)
        if self.mode == "feedback":
            self._remember_error(points_after_solve)

    def _remember_error(self, after: np.ndarray) -> None:
        """feedback: the candidate's error at this step's points (its answer minus the solve's
        final impulse, N s), kept by key for the next step; none where it fell back."""
        answer, self._answer = self._answer, None
        if answer is None or len(after) == 0:
            self._error_keys, self._error = np.zeros(0, np.uint64), np.zeros((0, 2))
            return
        keys, served = answer
        order = np.argsort(keys)
        rows = np.searchsorted(keys[order], after["key"]).clip(max=len(keys) - 1)
        found = keys[order][rows] == after["key"]
        error = served[order][rows[found]] - after["impulse"][found].astype(np.float64)
        by_key = np.argsort(after["key"][found])
        self._error_keys, self._error = after["key"][found][by_key], error[by_key]

    def pick(self, engine, points, served: list) -> tuple[np.ndarray, np.ndarray]:
        """The best for this step, by trial solves, of Box2D's warm start and the
        candidates' (`served`: (normal, tangent) each, or None for Box2D's own), or, by mode,
        the one it serves; every trial's iterations are kept in `trials`."""
        builtin = (np.ascontiguousarray(points["builtin"][:, 0]), np.ascontiguousarray(points["builtin"][:, 1]))
        candidates = [builtin] + [builtin if w is None else w for w in served]
        if self.mode == "feedback":
            self._answer = None if served[0] is None else (points["key"].copy(), _stacked(candidates[1]))
        derive = {"mean": self._mean, "admit": self._admitted, "motion": self._scaled_motion, "graft": self._grafted, "feedback": self._less_last_error,
                  "split": self._parts, "boost": self._parts, "shrink": self._shrunk, "gate": self._gated,
                  "face": self._on_faces, "solved": self._solved_on_labels,
                  "solved-forms": self._solved_on_labels, "jittered": self._jittered}.get(self.mode)
        if derive is not None:
            candidates += derive(engine, points, candidates)
        if self.mode.startswith("solved") and served[0] is None:  # the classifier fell back: no labels to solve on
            candidates[2:] = [builtin] * (len(candidates) - 2)
        traces = [engine.trial_trace(*w) for w in candidates]
        iterations = [len(t) for t in traces]
        self.trials.append(iterations)
        self.reach.append(sweeps_to_builtin(traces, engine.config.velocity_threshold))
        self.traced(traces)
        if self.mode in ("shadow", "split", "boost", "admit", "motion", "graft", "feedback"):
            return candidates[1]
        if self.mode in ("price", "shrink", "gate", "face"):
            return builtin  # the trials left the last candidate's as the step's warm start
        if self.mode == "mean":
            return candidates[-1]
        if self.mode.startswith("solved") or self.mode == "jittered":
            return candidates[2]
        return candidates[int(np.argmin(iterations))]  # argmin: the first, builtin, on a tie

    def traced(self, traces: list[np.ndarray]) -> None:
        """Called with each step's trial residual traces (builtin's first; (iterations,) N s
        each); a subclass that needs more of them than their lengths keeps them here."""

    # Each mode's derived warm starts, priced after builtin and the candidates. Each takes the
    # engine (after collide()), the step's point records and the candidates so far (builtin
    # first; (normal (P,), tangent (P,)) N s each) and returns a list of the same.

    def _jittered(self, engine, points, candidates) -> list:
        """jittered: the candidate plus NOISE N s of Gaussian noise at the points that persist
        (Box2D's warm start there is not zero), normal impulses clamped at 0."""
        warm = _stacked(candidates[1])
        persisting = points["builtin"].any(axis=1)[:, None]
        warm += np.where(persisting, self._rng.normal(0.0, self.NOISE, warm.shape), 0.0)
        return [_pushing(warm)]

    @staticmethod
    def _mean(engine, points, candidates) -> list:
        """mean: the candidates' mean."""
        return [as_warm_start(np.mean([_stacked(w) for w in candidates[1:]], axis=0))]

    def _admitted(self, engine, points, candidates) -> list:
        """admit: the candidate made admissible, whole, by its motion, by its motion with the
        points it pulls apart held open, and by its moving bodies' motion; the last not admitted."""
        from deepcontact.admission import nearest_admissible
        from deepcontact.kinematics import (Physics, bodies_moving, body_space_part, body_space_part_of,
                                            contact_velocities)

        bodies, mu = engine.bodies(), point_friction(self._friction, points)
        start, served = _stacked(candidates[0]), _stacked(candidates[1])
        motion = start + body_space_part(bodies, points, served - start)
        moving = start + body_space_part_of(bodies, points, served - start, bodies_moving(bodies))
        physics = Physics(engine.config.dt, tuple(engine.world.gravity))
        separating = contact_velocities(bodies, points, motion, physics)[:, 0] > SEPARATING_SPEED
        return [as_warm_start(nearest_admissible(bodies, points, w, mu, o))
                for w, o in ((served, None), (motion, None), (motion, separating), (moving, None))] + [_pushing(moving)]

    def _scaled_motion(self, engine, points, candidates) -> list:
        """motion: Box2D's warm start plus the candidate's motion times each of MOTION_SCALES,
        admitted; then its moving bodies' motion the same way."""
        from deepcontact.admission import nearest_admissible
        from deepcontact.kinematics import bodies_moving, body_space_part, body_space_part_of

        bodies, mu = engine.bodies(), point_friction(self._friction, points)
        start = _stacked(candidates[0])
        correction = _stacked(candidates[1]) - start
        motions = (body_space_part(bodies, points, correction),
                   body_space_part_of(bodies, points, correction, bodies_moving(bodies)))
        return [as_warm_start(nearest_admissible(bodies, points, start + k * m, mu))
                for m in motions for k in self.MOTION_SCALES]

    def _grafted(self, engine, points, candidates) -> list:
        """graft: the first candidate with the second's motion at the moving bodies, admitted and not."""
        from deepcontact.admission import nearest_admissible
        from deepcontact.kinematics import bodies_moving, body_space_part_of

        bodies = engine.bodies()
        base, donor = _stacked(candidates[1]), _stacked(candidates[2])
        grafted = base + body_space_part_of(bodies, points, donor - base, bodies_moving(bodies))
        return [as_warm_start(nearest_admissible(bodies, points, grafted, point_friction(self._friction, points))),
                _pushing(grafted)]

    def _less_last_error(self, engine, points, candidates) -> list:
        """feedback: the candidate less each of FEEDBACKS times its error on the previous step at
        the points that persist."""
        answer = _stacked(candidates[1])
        idx, persisting = persisting_rows(self._error_keys, points)
        warm = []
        for g in self.FEEDBACKS:
            w = answer.copy()
            w[persisting] -= g * self._error[idx[persisting]]
            warm.append(_pushing(w))
        return warm

    def _parts(self, engine, points, candidates) -> list:
        """split: Box2D's warm start plus each part of the candidate's correction alone (the
        part that moves the bodies, then the self-stress); boost: plus the whole correction
        with its self-stress scaled by each of BOOSTS."""
        from deepcontact.kinematics import body_space_part

        start = _stacked(candidates[0])
        correction = _stacked(candidates[1]) - start
        moves = body_space_part(engine.bodies(), points, correction)
        stress = correction - moves
        parts = (moves, stress) if self.mode == "split" else [moves + k * stress for k in self.BOOSTS]
        return [_pushing(start + part) for part in parts]

    def _shrunk(self, engine, points, candidates) -> list:
        """shrink: the reference (the second candidate) plus the first candidate's error against
        it: scaled whole by each of SHRINKS, then with its body-space part halved and with its
        self-stress halved (deepcontact.kinematics.body_space_part)."""
        from deepcontact.kinematics import body_space_part

        ref = _stacked(candidates[2])
        error = _stacked(candidates[1]) - ref
        moves = body_space_part(engine.bodies(), points, error)
        stress = error - moves
        # a part alone can pull; the whole never does
        return [_pushing(ref + k * error) for k in self.SHRINKS] + [_pushing(ref + 0.5 * moves + stress),
                                                                    _pushing(ref + moves + 0.5 * stress)]

    @staticmethod
    def _gated(engine, points, candidates) -> list:
        """gate: Box2D's warm start B moved toward the first candidate W at each point, judged by
        the second, E: all the way or not at all, whichever lies nearer E; by the share a in
        [0, 1] that minimises |B + a (W - B) - E| at the point; and by that share for normal and
        tangent apart."""
        b, w, e = (_stacked(x) for x in candidates[:3])
        step, want = w - b, e - b  # (P, 2) N s
        nearer = np.where((np.sum((w - e) ** 2, axis=1) < np.sum(want ** 2, axis=1))[:, None], w, b)
        length = np.sum(step ** 2, axis=1)
        share = np.clip(np.sum(step * want, axis=1) / np.where(length > 0, length, 1.0), 0.0, 1.0)
        apart = np.clip(step * want / np.where(step ** 2 > 0, step ** 2, 1.0), 0.0, 1.0)
        return [as_warm_start(x) for x in (nearer, b + share[:, None] * step, b + apart * step)]

    def _solved_on_labels(self, engine, points, candidates) -> list:
        """solved: the step solved on the candidate's face read as a classifier's labels
        (FACE_LABELS), admitted with the face's open points held at 0; solved-forms: then the
        same motion given Box2D's warm start's self-stress before the admission, the admission
        cut at SOLVED_ROUNDS rounds, and the labels read at each of SOLVED_PRESSING."""
        from deepcontact.admission import nearest_admissible
        from deepcontact.faces import OPEN, contact_face, solve_on_face, solved_on_labels
        from deepcontact.kinematics import Physics, body_space_part, contact_frame

        bodies, mu = engine.bodies(), point_friction(self._friction, points)
        frame = contact_frame(bodies, points)
        physics = Physics(engine.config.dt, tuple(engine.world.gravity))
        labels, builtin = _stacked(candidates[1]), _stacked(candidates[0])
        pressing, share = self.FACE_LABELS
        starts = []
        forms = self.mode == "solved-forms"
        for i, threshold in enumerate((pressing, *self.SOLVED_PRESSING) if forms else (pressing,)):
            starts.append(solved_on_labels(bodies, points, labels, mu, physics, threshold, share, frame=frame)[0])
            if forms and i == 0:  # Box2D's self-stress: its warm start less the part of it that moves the bodies
                face = contact_face(labels, mu, pressing=threshold, share=share)
                solved = solve_on_face(bodies, points, face, mu, physics, frame)
                change = builtin - solved
                kept = solved + change - body_space_part(bodies, points, change, frame)
                starts.append(nearest_admissible(bodies, points, kept, mu, open_points=face == OPEN, frame=frame))
                starts.append(nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, frame=frame,
                                                 iterations=self.SOLVED_ROUNDS))
        return [as_warm_start(x) for x in starts]

    def _on_faces(self, engine, points, candidates) -> list:
        """face: the step solved on the face (active set) of the reference E, the second
        candidate; on E's face with FACE_SWAPS of its labels, at random among the points where
        they differ, swapped for those of the first candidate W; with W's labels where either
        says the point is open (W's errors in which points press), then where both say it
        presses (its errors in which stick and which slide); on W's face; on W's face read as a
        classifier's labels (FACE_LABELS); and on Box2D's
        warm start's face (deepcontact.kinematics.contact_face, solve_on_face), each admitted
        with the face's open points held at 0; then Box2D's face and W's read as labels, each
        repaired (repair_face) once and again, each solve admitted. With E = oracle:near: how right must a learned
        active set be for the exact motion it implies to pay?"""
        from deepcontact.admission import nearest_admissible
        from deepcontact.faces import OPEN, contact_face, face_errors, repair_face, solve_on_face
        from deepcontact.kinematics import Physics, contact_frame

        bodies, mu = engine.bodies(), point_friction(self._friction, points)
        frame = contact_frame(bodies, points)
        physics = Physics(engine.config.dt, tuple(engine.world.gravity))
        builtin, guess, reference = (contact_face(_stacked(w), mu) for w in candidates[:3])
        differ = np.flatnonzero(guess != reference)
        self.notes.append([len(points), *face_errors(guess, reference), *face_errors(builtin, reference)])
        rng = np.random.default_rng(len(self.trials))  # the same swaps at the same step in every run
        faces = [reference]
        for k in self.FACE_SWAPS:
            face = reference.copy()
            swap = rng.choice(differ, size=min(k, len(differ)), replace=False) if len(differ) else differ
            face[swap] = guess[swap]
            faces.append(face)
        either_open = (guess == OPEN) | (reference == OPEN)
        pressing, share = self.FACE_LABELS
        faces += [np.where(either_open, guess, reference), np.where(either_open, reference, guess), guess, builtin,
                  contact_face(_stacked(candidates[1]), mu, pressing=pressing, share=share)]

        def solved(face):  # (P,) labels -> (P, 2) N s: solved on them, admitted
            return nearest_admissible(bodies, points, solve_on_face(bodies, points, face, mu, physics, frame), mu,
                                      open_points=face == OPEN, frame=frame)

        starts = [solved(f) for f in faces]
        for start in starts[-2:]:  # builtin's face, then W's read as labels: each repaired FACE_REPAIRS times
            for _ in range(self.FACE_REPAIRS):
                start = solved(repair_face(bodies, points, start, mu, physics))
                starts.append(start)
        return [as_warm_start(x) for x in starts]


def sweeps_to_builtin(traces: list[np.ndarray], threshold: float) -> list[int]:
    """Each trial's sweeps until it is as near converged as Builtin's trial ended.

    traces: builtin's first, then each candidate's residual trace ((iterations,)
    float32, N s: the largest impulse change of each sweep). Where Builtin
    converges the mark is the stopping threshold, so each count is the trial's
    iterations; where it ends at the cap the mark is its last change, which the
    iteration count cannot see: a start that gets there sooner is worth those
    sweeps. A trial that never reaches the mark counts all its sweeps (a lower
    bound on what it would need).
    """
    last = float(traces[0][-1]) if len(traces[0]) else 0.0
    mark = np.float32(max(last, threshold))
    reach = []
    for t in traces:
        below = np.flatnonzero(t <= mark)
        reach.append(int(below[0]) + 1 if below.size else len(t))
    return reach


def _stacked(warm) -> np.ndarray:
    """A warm start (normal (P,), tangent (P,)) N s as one (P, 2) float64 array."""
    return np.stack(warm, axis=1).astype(np.float64)


def _pushing(impulses: np.ndarray):
    """(P, 2) N s as a warm start with no normal impulse below 0 (a contact only pushes)."""
    return as_warm_start(np.column_stack([np.maximum(impulses[:, 0], 0.0), impulses[:, 1]]))


#: One line per mode, as help lists them (the module docstring says each in full).
MODE_HELP = {
    "pick": "keeps, each step, the cheapest of builtin and W1, W2, ... by trial solves",
    "shadow": "serves W1 and prices builtin and the others on its states",
    "mean": "serves the mean of W1, W2, ... and prices it beside each",
    "price": "serves builtin and prices W1, W2, ... on its states (the same in every run)",
    "split": "serves W and prices the two parts of its correction (body-space, self-stress)",
    "boost": "serves W and prices it with its self-stress part scaled",
    "admit": "serves W and prices forms of it admitted into the friction cones",
    "motion": "serves W and prices its motion scaled and admitted",
    "graft": "serves W1 and prices it with W2's moving bodies' motion",
    "feedback": "serves W and prices it less shares of its previous step's error",
    "shrink": "serves builtin and prices W's error against E scaled, and its two parts halved",
    "gate": "serves builtin and prices W gated per point against builtin, judged by E",
    "face": "serves builtin and prices the step solved on E's active set, with W's labels, and on W's",
    "solved": "serves the step solved on classifier W's labels, admitted (the face route, closed loop)",
    "solved-forms": "serves as solved:W does and prices other forms of it",
    "jittered": "serves W plus noise far below the tolerance: another draw of W's closed loop",
}
#: How each mode's name is written in help.
MODE_USAGE = {"pick": "W1+W2+...", "shadow": "W1+W2+...", "mean": "W1+W2+...", "price": "W1+W2+...",
              "graft": "W1+W2", "shrink": "W+E", "gate": "W+E", "face": "W+E"}


def make_composite(name: str) -> Pick:
    """MODE:W1+W2+... (or solved@P:W, solved-forms@P:W, jittered@S:W) as a Pick; ValueError saying what is wrong."""
    if name.startswith("jittered@"):  # jittered@S:W, S N s of noise on W's answer
        size, colon, rest = name[len("jittered@"):].partition(":")
        try:
            noise = float(size)
        except ValueError:
            noise = None
        if not colon or noise is None:
            raise ValueError(f"jittered@S: needs a noise size in N s, e.g. jittered@1e-7:server:NAME, got {name!r}")
        return Pick(make_composite(f"jittered:{rest}").candidates, mode="jittered", noise=noise)
    for mode in ("solved", "solved-forms"):  # solved@P:W: W's labels read pressing above P N s
        if name.startswith(f"{mode}@"):
            threshold, colon, rest = name[len(mode) + 1:].partition(":")
            try:
                pressing = float(threshold)
            except ValueError:
                pressing = None
            if not colon or pressing is None:
                raise ValueError(f"{mode}@P: needs a pressing threshold in N s, e.g. {mode}@0.75:server:NAME, "
                                 f"got {name!r}")
            return Pick(make_composite(f"{mode}:{rest}").candidates, mode=mode, pressing=pressing)
    mode, _, rest = name.partition(":")
    names = [n for n in rest.split("+") if n]
    if not names or any(composite_parts(n) is not None for n in names):
        raise ValueError(f"{mode}: takes warm starts joined by +, e.g. {mode}:server:default+server:pressure, "
                         f"got {name!r}")
    if any(n in ("none", "builtin") for n in names):
        raise ValueError(f"{mode}: always tries builtin; for zeros use server:zero, got {name!r}")
    return Pick([make_provider(n) for n in names], mode=mode)


for _mode in Pick.MODES:
    register_prefix(f"{_mode}:", make_composite, MODE_HELP[_mode], usage=f"{_mode}:{MODE_USAGE.get(_mode, 'W')}",
                    composite=True)
for _mode in ("solved", "solved-forms"):
    register_prefix(f"{_mode}@", make_composite, f"{_mode}:W with W's labels read pressing above P N s",
                    usage=f"{_mode}@P:W", composite=True)
register_prefix("jittered@", make_composite, "jittered:W with noise of S N s", usage="jittered@S:W", composite=True)
