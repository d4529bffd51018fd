"""What a route has cost at each step size, to tell whether it fits a step's deadline.

A face card's route (the classifier, the solve on its labels, the admission) grows with the
step's size, by a power that differs from world to world (its served CPU time, from about 40
points to about 600, grew as the 0.9th power of (size + OFFSET) on Box2D's Pyramid and, from
about 30 to about 150, as the 1.7th on the thesis world's piles of discs), and it differs from
host to host by a factor of three: a threshold fixed in the card would be wrong somewhere. A
`CostBySize` learns it on the host that serves, from the steps it serves:

    cost = CostBySize()
    if cost.fits(len(points), time.perf_counter(), deadline):   # deadline: perf_counter() s
        ... the dear route ...
        cost.observe(len(points), seconds)
    else:
        ... the cheap one ...

Steps are grouped by size in buckets of BUCKET_POINTS points. A bucket with TRIALS steps
seen or more is estimated by the QUANTILE of its last WINDOW steps, so that steps that run
long on a busy host (the reason for the deadline) count. A bucket with fewer is estimated from
the nearest smaller one that has them, grown with a power of (size + OFFSET) (OFFSET: the
route's fixed costs, the classifier's and the solve's set-up): the power the known buckets
show between the smallest and the largest of them, where those lie at least SPREAD apart in
(size + OFFSET), held between MIN_POWER and MAX_POWER; DEFAULT_POWER until then. (Grown with
the square, a route that had seen only a pile's first steps, of about 40 points, expected 6 ms
at 110 and 34 ms at 320 where it took 3 and 5, and no larger step was ever tried: Box2D's
Pyramid served Box2D's start on 119 of its 129 steps.) With none such, from the steps seen
within NEAR of its size, each scaled so to it, by their median (steps of several sizes, and a
cold first call among them), once there are TRIALS of them: a stream whose steps change by
more than a bucket from one step to the next fills no bucket for a while, and each new size
would otherwise be tried and run late in turn (a pyramid of 600 points on a fresh server: its
first 30 steps). Not from farther: a few small steps' cold costs grown to a large size turned
every later step of a stream away.
With fewer, the route fits, unless the server is busy (a slowdown of BUSY or more: another
step shares each core), when it is only probed. So a
size a little larger than those known is tried and learned, one far larger is not tried until
the sizes between are known, and one cold first call (planning, imports) decides nothing. A
bucket turned away is tried again on every PROBE_EVERY-th step declined where its fastest
recent step would still fit, so that an estimate a busy moment raised comes down again.
"""

from __future__ import annotations

import collections
import math
import threading


BUCKET_POINTS = 10
WINDOW = 16
QUANTILE = 0.9
PROBE_EVERY = 16
TRIALS = 3
OFFSET = 50
#: The power of (size + OFFSET) a cost grows with, learned between these bounds from the known
#: buckets where they lie at least SPREAD apart in (size + OFFSET); DEFAULT_POWER until then.
MIN_POWER, DEFAULT_POWER, MAX_POWER = 1.0, 1.5, 2.0
SPREAD = 1.5
#: The share of a step's size within which steps of other sizes speak for it while no bucket at
#: or below it is known.
NEAR = 0.2
#: A slowdown at which the server counts as busy: another step at least shares each core.
BUSY = 2.0

def _quantile(ordered: list[float], q: float) -> float:
    """numpy.quantile's default (linear) of a few sorted numbers, without its overhead (a served
    step asks once)."""
    at = q * (len(ordered) - 1)
    low = int(at)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (at - low)


def _grow(seen: int, asked: int, power: float = DEFAULT_POWER) -> float:
    """The factor from a step's cost in bucket `seen` to one in bucket `asked`: (size + OFFSET)
    to the `power`."""
    return 1.0 if seen == asked else ((asked * BUCKET_POINTS + OFFSET) / (seen * BUCKET_POINTS + OFFSET)) ** power


def _power(known: dict[int, float]) -> float:
    """The power of (size + OFFSET) that a route's cost grows with, from its known buckets'
    median seconds ({bucket: s}): between the smallest and the largest where they lie SPREAD
    apart, held inside [MIN_POWER, MAX_POWER]; DEFAULT_POWER where none do."""
    if len(known) < 2:
        return DEFAULT_POWER
    low, high = min(known), max(known)
    ratio = (high * BUCKET_POINTS + OFFSET) / (low * BUCKET_POINTS + OFFSET)
    if ratio < SPREAD or known[low] <= 0.0 or known[high] <= 0.0:
        return DEFAULT_POWER
    return min(MAX_POWER, max(MIN_POWER, math.log(known[high] / known[low]) / math.log(ratio)))


class CostBySize:
    """Recent costs of a route by step size (points), seconds; thread-safe."""

    def __init__(self) -> None:
        self._seen: dict[int, collections.deque] = {}
        self._medians: dict[int, float] = {}  # the median seconds of each bucket with TRIALS steps seen
        self._power = DEFAULT_POWER  # _power(self._medians), kept as steps are observed
        self._declined: collections.Counter = collections.Counter()
        self._lock = threading.Lock()

    def observe(self, points: int, seconds: float) -> None:
        """One step of `points` points took `seconds` s along the route."""
        k = points // BUCKET_POINTS
        with self._lock:
            recent = self._seen.setdefault(k, collections.deque(maxlen=WINDOW))
            recent.append(float(seconds))
            if len(recent) >= TRIALS:
                self._medians[k] = _quantile(sorted(recent), 0.5)
                self._power = _power(self._medians)

    def estimate(self, points: int) -> float:
        """Seconds the route is expected to take on a step of `points` points (0: nothing known
        at this size or below, and fewer than TRIALS steps seen at any size)."""
        return self._estimate(points)[0]

    def _estimate(self, points: int) -> tuple[float, float]:
        """(the estimate, the fastest recent step's seconds) at this size, as the module says."""
        k = points // BUCKET_POINTS
        with self._lock:
            power = self._power
            known = [b for b in self._medians if b <= k]
            if not known:
                near = max(1.0, NEAR * points / BUCKET_POINTS)  # in buckets; the next ones always
                pooled = sorted(seconds * _grow(b, k, power) for b, recent in self._seen.items()
                                if abs(b - k) <= near for seconds in recent)
                if len(pooled) < TRIALS:
                    return 0.0, 0.0
                return _quantile(pooled, 0.5), pooled[0]
            b = max(known)
            values = sorted(self._seen[b])
        grow = _grow(b, k, power)
        return grow * _quantile(values, QUANTILE), grow * values[0]

    def fits(self, points: int, now: float, deadline: float | None, slowdown: float = 1.0) -> bool:
        """Whether a step of `points` points started along the route at `now` should take it
        to end by `deadline` (both time.perf_counter() s; None: no deadline, it always fits).
        slowdown: how many times its own time the route's wall time is expected to take (the
        requests the server is answering at once over its cores: they share them)."""
        if deadline is None:
            return True
        expected, fastest = self._estimate(points)
        if expected == 0.0 and slowdown >= BUSY:
            # Nothing known at this size on a server answering several steps at once: a guess
            # that ran late would make every step sharing the cores late too. Probed below.
            expected = float("inf")
        expected, fastest = expected * slowdown, fastest * slowdown
        if now + expected <= deadline:
            return True
        k = points // BUCKET_POINTS
        with self._lock:
            self._declined[k] += 1
            probe = self._declined[k] % PROBE_EVERY == 0
        return probe and now + fastest <= deadline
