"""The guard: serve the learned warm start only while it beats Box2D's own.

A warm start learned on one kind of world can cost another kind many times
Box2D's own iterations (a stack of boxes is not a pile of discs). The guard
measures, on the simulation's own steps, both starts on the same state, and
serves whichever is cheaper:

    guard = Guard()
    plan = guard.plan()                      # on each step with contacts, before asking
    # plan.ask: ask the server this step; plan.probe: price both starts on it
    guard.served("builtin", sweeps)          # a step that was not a probe
    guard.probed(learned=..., builtin=..., trial_sweeps=..., builtin_sweeps=...)

A probe prices the start that is not served with the engine's trial solve (a
velocity solve that leaves the world as it was) and solves the step from the
served one: one paired comparison for the cost of one extra velocity solve.
The guard starts on Box2D's own start, so a world where the learned start
loses never serves it, and switches to the learned start once its paired
sweeps over the last probes come to at most `enter` of Box2D's; it switches
back where they exceed `leave`. Probes come often at first and after a switch,
then less often (their interval doubles while they agree), sooner when a
learned step costs far more than Box2D's recent steps did (`alarm`), and
never past a budget: the trial sweeps stay under `budget` of the sweeps Box2D's
own start has been needing, so the guard costs at most that share of Box2D's
solve time. A trial of the learned start stops at `cap` times Box2D's recent
sweeps: past that it has lost, and how badly does not matter.

The server also says, with each answer, whether the step lies inside what its
model was trained on (deepcontact.envelope; `heard`). On a familiar world the
model's gain has been measured before the run, so the guard trusts it: the
learned start serves from the first step, probes go on within the budget, and
only a full window of probes that says it loses ends its turn; no single
step's loss (a severe probe, a panic) does, nor a world at rest. An unfamiliar
world is held to Box2D's start until its own probes say otherwise.

With no stopping tolerance every step runs the same number of sweeps; a step's
cost is then how far from converged its start leaves it (the last sweep's
largest impulse change, N s), and the guard compares that instead.
"""

from __future__ import annotations

import collections
import dataclasses

LEARNED = "learned"
BUILTIN = "builtin"


@dataclasses.dataclass(frozen=True)
class GuardSettings:
    """budget: trial sweeps per sweep of Box2D's own start that scheduled probes may spend (0.03:
        3 %; the first probes and the rechecks of alarms come on top: on Box2D's Pyramid, where
        the learned start and Box2D's are even and probing never stops, 3.5 % came to 5.1 % of
        Box2D's sweeps and 3 % to 4.8 %, docs/research/2026-12-06-the-guards-budget.md).
    window: the last paired probes a decision reads.
    enter, leave: the learned start is served from a paired ratio (its cost over
        Box2D's, summed over the window) at most `enter`, and left above `leave`.
    severe: a probe whose learned start cost more than this many times Box2D's ends
        the learned start's turn, whatever the window says.
    interval: (first, longest) steps with contacts between probes.
    alarm: where the learned start's recent steps (their median) cost more than this
        many times Box2D's reference (an unpaired comparison, so only a warning), the
        next step is a probe, whatever the budget, at most once an interval's length
        (`interval[1]`); a single learned step at `panic` times the world's recent
        steps (scale()) hands the next steps to Box2D's start at once.
    cap: a trial of the learned start stops at this many times Box2D's recent sweeps.
    free_probes: probes made whatever the budget (the first ones, on a run's first
        steps with contacts, before any budget has been earned).
    history: where the last this many paired probes, summed, still say the learned start
        wins (at most `enter`), a window that says otherwise does not end its turn (only a
        probe lost by more than `severe`, or a panic, does).
    recent: how many of Box2D's last measured steps (served or priced) its reference,
        their median, is taken over.
    floor: where Box2D's recent steps took fewer sweeps than this, its own start is
        served (probes go on, as cheap as those steps): a learned start could save a step
        at most those few sweeps and can cost it hundreds (a stack at rest needs one or two).
    trust: serve the learned start from the first step of a world the server calls familiar
        (module docstring); False holds every world to Box2D's start until probes say otherwise.
    ask_first: steps with contacts on which the guard asks the server before it has heard
        whether the world is familiar (the first answer says; a step that gets none, a late or
        failed one, asks again on the next, up to this many).
    checks: probes made whatever the budget while a trusted start serves (a familiar world's
        first steps, when they are cheap): a model that loses on the worlds it was trained
        on (the thesis's Pressure CNN) is found out within a few dozen steps.
    verdict: on a familiar world, the learned start goes where its last `verdict` probes lost in
        sum and in the median probe (robust to one busy step at the solver's cap), or a full
        `window` lost by more than `leave`."""

    budget: float = 0.03
    window: int = 8
    enter: float = 0.9
    leave: float = 1.2
    severe: float = 3.0
    interval: tuple[int, int] = (2, 16)
    alarm: float = 3.0
    panic: float = 10.0
    cap: float = 1.0
    free_probes: int = 2
    recent: int = 9
    history: int = 24
    floor: float = 5.0
    trust: bool = True
    ask_first: int = 3
    checks: int = 4
    verdict: int = 4

    def __post_init__(self) -> None:
        if not (0 <= self.budget < 1 and self.window >= 1 and 0 < self.enter <= self.leave <= self.severe
                and 1 <= self.interval[0] <= self.interval[1] and self.cap >= 1 and self.alarm >= 1
                and self.recent >= 1 and self.floor >= 0 and self.panic >= self.alarm):
            raise ValueError(f"inconsistent guard settings: {self}")


@dataclasses.dataclass(frozen=True)
class Plan:
    """What the guard wants of one step with contacts: ask the server for the learned
    start (`ask`), and price both starts on it (`probe`, implies ask)."""

    ask: bool
    probe: bool


class Guard:
    """One simulation's guard (state across its steps). `mode` is the start it serves:
    BUILTIN (Box2D's own) or LEARNED."""

    def __init__(self, settings: GuardSettings = GuardSettings()):
        self.settings = settings
        self.mode = BUILTIN
        self.pairs: collections.deque[tuple[float, float]] = collections.deque(maxlen=settings.window)
        self.history: collections.deque[tuple[float, float]] = collections.deque(maxlen=settings.history)
        self._recent: collections.deque[float] = collections.deque(maxlen=settings.recent)
        self._learned: collections.deque[float] = collections.deque(maxlen=settings.recent)  # served learned steps
        self.reference: float | None = None  # Box2D's recent sweeps a step: the median of the last `recent` seen
        self.earned = 0.0  # trial sweeps the budget allows so far
        self.spent = 0  # trial sweeps made
        self.interval = settings.interval[0]
        self.countdown = 0  # steps with contacts until the next probe is due
        self.pending = False  # an alarm asked for a probe
        self.below_floor = False  # the last plan found Box2D's reference under the floor
        self.since_alarm = settings.interval[1] + 1  # learned steps since the last alarm
        self.since_panic = settings.interval[1] + 1  # learned steps since the last panic
        self.probes = 0
        self.switches = 0
        self.familiar: bool | None = None  # the server's last word on this world (None: not heard yet)
        self.unfamiliar = ""  # why the server last called it unfamiliar
        self.trusted = False  # the learned start serves because the world is familiar, not yet by probes
        self.asked = 0  # steps asked before the server was heard

    # -- before a step -----------------------------------------------------
    def plan(self) -> Plan:
        """Called once per step with contacts, before the warm start is chosen."""
        if self.familiar is None and self.settings.trust and self.asked < self.settings.ask_first:
            self.asked += 1
            return Plan(ask=True, probe=False)  # the answer says whether the world is familiar
        if self.reference is None:  # nothing measured of Box2D's start yet
            if self.mode == LEARNED:  # a trusted start: its first probes are free
                return Plan(ask=True, probe=self.countdown <= 0 and self._affordable())
            return Plan(ask=False, probe=False)  # the first step with contacts sets the scale of everything
        if self.familiar:
            pass  # a familiar world's start serves at rest too: its gain there was measured, not guessed
        elif self.reference < self.settings.floor:
            if self.mode == LEARNED:
                self._switch(BUILTIN)  # a world at rest: no learned start there (probes go on, cheap, for later)
            self.below_floor = True
        elif self.below_floor:  # the world just got busy enough for a learned start: find out now
            self.below_floor, self.pending = False, True
        # An alarm's recheck is made whatever the budget says (alarms come at most one an
        # interval's length apart); a scheduled probe waits until the budget allows it.
        probe = self.pending or (self.countdown <= 0 and self._affordable())
        return Plan(ask=probe or self.mode == LEARNED, probe=probe)

    def trial_cap(self) -> int:
        """Sweeps past which a trial of the learned start has lost: ceil(cap x scale())."""
        return max(1, int(-(-self.settings.cap * (self.scale() or 1.0) // 1)))

    def scale(self) -> float:
        """How many sweeps the world's steps have been needing: Box2D's reference, or the
        learned start's own recent steps where larger (Box2D's is measured at probes only
        while the learned start serves, and a world that gets busier outgrows it)."""
        return max(self.reference or 0.0, _median(self._learned))

    def _affordable(self) -> bool:
        """Whether the budget allows a scheduled probe now: what it is expected to cost (a trial of
        Box2D's start, the reference; of the learned start, the reference times the paired ratio
        seen so far, up to the cap) within what has been earned."""
        if self.probes < (self.settings.checks if self.trusted else self.settings.free_probes):
            return True
        share = 1.0
        if self.mode == BUILTIN:
            seen = self.ratio()
            share = self.settings.cap if seen is None else min(self.settings.cap, max(0.25, seen))
        return self.spent + share * self.reference <= self.earned

    # -- the server's word -------------------------------------------------
    def heard(self, familiar: bool, why: str = "") -> None:
        """The server's answer to this step says whether the world lies inside what its model
        was trained on (why: the reason where not). A familiar world's learned start is trusted
        (served from now, until a full window of probes says it loses); a world that stops
        being familiar (a body of another kind added) loses that trust at once."""
        if not self.settings.trust:
            return
        first = self.familiar is None
        self.familiar, self.unfamiliar = familiar, "" if familiar else why
        if familiar and first and self.mode == BUILTIN:
            self.trusted = True
            self._switch(LEARNED)
        elif not familiar and self.trusted:
            self.trusted = False
            if self.mode == LEARNED:
                self._switch(BUILTIN)

    # -- after a step ------------------------------------------------------
    def served(self, start: str, cost: float, sweeps: int) -> None:
        """A step with contacts that was not a probe: `start` (LEARNED or BUILTIN) was served
        and cost `cost` (its sweeps, or its last residual without a tolerance) in `sweeps`."""
        self.countdown -= 1
        if start == BUILTIN:
            self._learn_reference(sweeps)
            self.earned += self.settings.budget * sweeps
            return
        self.earned += self.settings.budget * (self.reference or sweeps)
        scale = self.scale()
        self._learned.append(float(sweeps))
        self.since_alarm += 1
        self.since_panic += 1
        if self.reference is None or self.familiar:  # a familiar world's turn ends only by its probes
            return
        if sweeps > self.settings.panic * scale:
            self._switch(BUILTIN)  # far worse than the world has been needing: no second such step
            if self.since_panic > self.settings.interval[1]:  # and a recheck, in case the world just got busier
                self.since_panic, self.pending = 0, True
        elif _median(self._learned) > self.settings.alarm * self.reference and self.since_alarm > self.settings.interval[1]:
            # The learned start's recent steps cost more than Box2D's last measured ones: maybe the
            # world got busier, maybe the learned start went wrong. The next step is a probe.
            self.since_alarm = 0
            self.pending = True

    def probed(self, *, learned: float, builtin: float, trial_sweeps: int, builtin_sweeps: int,
               capped: bool = False) -> None:
        """A probe: both starts' costs on the same state (`learned`, `builtin`), the trial's
        sweeps and Box2D's start's sweeps on it (trial or solve). capped: the learned start's
        trial stopped at trial_cap(), so its cost is only known to be at least `learned`; where
        Box2D's start cost as much or more, the probe tells nothing and is not counted."""
        self.probes += 1
        self.spent += trial_sweeps
        self.pending = False
        self._learn_reference(builtin_sweeps)
        self.earned += self.settings.budget * builtin_sweeps
        if capped and builtin >= learned:
            self.countdown = self.settings.interval[0]  # soon again, once the reference has caught up
            return
        self.pairs.append((float(learned), float(builtin)))
        self.history.append((float(learned), float(builtin)))
        switched = self._decide()
        longest = self.settings.interval[1]
        self.interval = self.settings.interval[0] if switched else min(2 * self.interval, longest)
        self.countdown = self.interval

    def ratio(self) -> float | None:
        """The learned start's cost over Box2D's, summed over the last paired probes."""
        return _sum_ratio(self.pairs) if self.pairs else None

    def _decide(self) -> bool:
        """Switch where the window says so; True when it did. A sum over the window weighs
        probes by their sweeps, so one busy step can outvote several quiet ones: the last probe,
        the best guess at the next steps, must agree (no loss to enter, no loss by more than
        `severe` to stay)."""
        ratio = self.ratio()
        learned, builtin = self.pairs[-1]
        last = learned / builtin if builtin > 0 else (1.0 if learned == 0 else float("inf"))
        if (self.mode == BUILTIN and len(self.pairs) >= min(2, self.settings.window) and ratio <= self.settings.enter
                and last <= 1.0 and (self.familiar or self.reference >= self.settings.floor)):
            self._switch(LEARNED)
            return True
        if self.familiar:
            # A familiar world's learned start goes only where a whole window of probes says it
            # loses: its gain was measured on such worlds, and a busy pile's paired ratio swings
            # several-fold from step to step (one step at the solver's cap is not the world).
            recent = list(self.pairs)[-self.settings.verdict:]
            lost = len(recent) >= self.settings.verdict and _sum_ratio(recent) > 1.0 and _median(
                [(l + 1.0) / (b + 1.0) for l, b in recent]) > 1.0
            if self.mode == LEARNED and (lost or len(self.pairs) >= self.settings.window and ratio > self.settings.leave):
                self._switch(BUILTIN)
                return True
            return False
        # A learned start that has been winning over many probes keeps serving through a window
        # of bad luck: in a busy pile a step's paired ratio swings several-fold, and each turn
        # on Box2D's start costs the steps until the next probe. Where it loses in the long run
        # too, or a probe loses badly, it goes.
        settled = len(self.history) >= self.settings.history and self.long_ratio() <= self.settings.enter
        if self.mode == LEARNED and ((ratio > self.settings.leave and not settled) or last > self.settings.severe):
            self._switch(BUILTIN)
            return True
        return False

    def long_ratio(self) -> float:
        """The learned start's cost over Box2D's over the last `history` paired probes."""
        learned = sum(p[0] for p in self.history)
        builtin = sum(p[1] for p in self.history)
        return learned / builtin if builtin > 0 else 1.0

    def _switch(self, mode: str) -> None:
        if mode == BUILTIN:
            self.trusted = False
        self.mode = mode
        self.switches += 1
        self.interval = self.settings.interval[0]
        self.countdown = self.interval

    def _learn_reference(self, sweeps: int) -> None:
        # A median, not a mean: one step at the cap must not make a resting world look like a busy one.
        self._recent.append(float(sweeps))
        self.reference = _median(self._recent)


def _sum_ratio(pairs) -> float:
    """The learned start's cost over Box2D's, summed over (learned, builtin) pairs."""
    learned, builtin = sum(p[0] for p in pairs), sum(p[1] for p in pairs)
    return learned / builtin if builtin > 0 else (1.0 if learned == 0 else float("inf"))


def _median(values) -> float:
    """The upper median of a few numbers (0 for none)."""
    ordered = sorted(values)
    return float(ordered[len(ordered) // 2]) if ordered else 0.0
