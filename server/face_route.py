"""The face route: a step solved on a classifier's labels and admitted into the friction cones.

A graph card with `face` (deepcontact.modelcard) is served by a FaceRoutePredictor, built
whole by server.predictors.load_model from three parts:

    classifier  a GraphPredictor trained on the recorded solve's labels (`train-graph
                --targets face`): about 1 N s along the normal where a point presses, +-1 N s
                along the tangent where it slides; with the card's `mirror`, a
                server.mirror_image.MirroredGraphPredictor, whose reflected half runs on the
                spare core beside the step's (the plain network's half alone on a busy server
                or a host of one core)
    fallback    the predictor of the card its face names (`fallback`), served where the route
                is not and the step lies inside the fallback's training envelope (its card's
                trained_on); elsewhere, or None: Box2D's warm start, the request's builtin impulses.
                It may be another face card, whose route is then tried in turn where this
                one's did not run (the default falls back to the route of a classifier trained
                on a zoo of worlds); where this one's ran and missed, that card's own fallback
                answers: two routes on one step would double its cost
    settings    the card's `face` dict: how the labels are read, solved and admitted, and when
                the route is not taken (max_points, max_residual, retry_pressing)

The route answers only for the worlds its classifier was trained on (the card's trained_on;
everywhere where it records none): on a stack of boxes a classifier trained on piles of discs
labelled about one point in twenty wrong, and the solve on those labels cost 2.4x Builtin's
iterations on the same states (docs/research/2026-12-06-a-zoo-of-worlds.md). Elsewhere the
fallback answers.

Per step, where the route fits (not past max_points, and expected to end by the request's
deadline, learned per step size on this host: server.deadline.CostBySize), the classifier's
answer is read as labels, the step solved on them (deepcontact.faces.read_and_solve) and the
result admitted (deepcontact.faces.admit_solved, admission.nearest_admissible's rounds, none
begun after the deadline; with the card's min_rounds the route fits where it would end in that
many rounds, and its rounds end where the check after them would still end by the deadline); where the admitted solve misses its labels by more than
max_residual, the labels are read again at each of retry_pressing's thresholds (none begun
after the deadline), and the fallback answers where no reading meets it. With the card's
against_builtin, an answer that one projected Jacobi step would change more than it would change
Box2D's warm start (deepcontact.kinematics.jacobi_change), or with its check_sweeps the solver's
N-th sweep (deepcontact.faces.sweep_changes), is not served: Box2D's is ("builtin"); with its
check_stop too, where the client declared its stopping rule (World.tolerance), the sweeps each
start takes to it decide (deepcontact.faces.sweeps_to_stop). With the
card's carry, the admission of a stream's step begins where the same points' stopped on the step
before (deepcontact.admission.AdmissionCarry, kept in the memory the server keeps per stream
and model). With its repairs (and by_island), the route's answer is repaired up to that many
times in turn, each the step solved again on the labels one step of an active-set method reads off
the answer before it (deepcontact.faces.repair_face), none begun where it would not end in time, and
the check serves each island whichever of Box2D's start, the answer and its repairs stops it
soonest. Its Prediction's stages:

    features   the classifier's point channels
    inference  the classifier's network (with a mirrored classifier also the route's geometry,
               built here while the reflected half runs on the spare core)
    solve      its output read as labels (denormalized, combined) and the step solved on them
    admit      the admission into the cones and the labels' residual (and a step gate's verdict,
               and with against_builtin the comparison with Box2D's start)

Where the fallback answers, its own stages are added in and `served_by` names it ("builtin"
for Box2D's warm start).
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import threading
import time

import numpy as np

from deepcontact.admission import AdmissionCarry
from deepcontact.faces import (LABELS_FRICTION, admit_solved, contact_face, face_labels, island_sweeps_to_stop,
                               prepare_route, read_and_solve, repair_face, route_compiled, sweep_changes,
                               sweeps_to_stop)
from deepcontact.kinematics import contact_frame, effective_masses, jacobi_change
from deepcontact.modelcard import ModelCard, ModelCardError
from deepcontact.step_gate import StepGate, step_features
from server.deadline import CostBySize
from server.held_labels import HeldLabels
from server.mirror_image import MirroredGraphPredictor
from server.predictors import Domain, GraphPredictor, Prediction, Predictor, World

#: What the route reads beyond its classifier's inputs: it solves the step's contact problem,
#: so the bodies' inertia, the step's physics, each point's friction, and Box2D's warm start
#: (the answer where no fallback card is named).
ROUTE_NEEDS = ("body_inertia", "physics", "point_friction", "builtin")
#: served_by where Box2D's warm start is served in the route's place (no fallback card).
BUILTIN = "builtin"
#: The fewest points at which a step's geometry is built ahead, on another core: below, the
#: hand-off costs about what it saves.
AHEAD_POINTS = 60
#: served_by's ending where the route answered on labels its classifier gave an earlier step of
#: the stream (the card's held_labels: server.held_labels).
HELD = " (held labels)"


class FaceRoutePredictor(Predictor):
    """A face card's warm start (module docstring): card, the face card itself (its name,
    description, `face` settings and optional `step_gate`); classifier, the GraphPredictor of
    its network, built from the card without face and gate; fallback, the predictor of the
    card its face names, or None for Box2D's warm start."""

    takes_deadline = True
    takes_memory = True  # predict(..., memory=): a stream's state between its steps (the card's carry)
    takes_restitution = True  # predict(..., restitution=): each point's, the request's point_restitution

    def __init__(self, card: ModelCard, classifier: GraphPredictor, fallback: Predictor | None = None):
        if card.face is None:
            raise ModelCardError(f"{card.name}: the face route serves a card with face")
        self.card, self.name, self.kind, self.description = card, card.name, card.kind, card.description
        # The classifier's training worlds (the route answers for the worlds it labels), the route's measured gain.
        self.envelope, self.wins_where_trained = card.envelope, card.wins_where_trained
        self.gridspec = card.gridspec
        self.settings = card.face
        self.extrapolates_jointed = self.settings["extrapolate_jointed"]
        self.classifier = classifier
        self.fallback = fallback
        # A gate on the card decides between the route's answer and Box2D's, as on a graph card.
        self.gate = StepGate.from_dict(card.step_gate) if card.step_gate is not None else None
        gate_needs = ("builtin", "point_separation") if self.gate is not None else ()
        self.requires = tuple(sorted(set(classifier.requires) | set(ROUTE_NEEDS) | set(gate_needs)
                                     | set(fallback.requires if fallback is not None else ())))
        # The route's seconds by step size, on this host: with the card's min_rounds, its seconds
        # had its admission stopped at min_rounds (what fits asks); and the check's seconds a sweep
        # (where the admission's rounds past min_rounds must stop: the check's sweeps vary from
        # step to step far more than its cost a sweep does).
        self.cost = CostBySize()
        self.held_cost = CostBySize()  # the route's on held labels: without its classifier
        self.sweep_cost = CostBySize()
        self.fallback_cost = CostBySize()  # the fallback card's
        # A step with a budget runs the route only in a free lane, one a core: on a server
        # answering several streams at once, routes that ran side by side stretched one another
        # past their budgets (4 streams on one core: 2.5 % of steps late); the step that finds
        # every lane busy is answered by the fallback at once.
        cores = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
        self._lanes = threading.BoundedSemaphore(cores)
        # A thread that builds a step's geometry while its classifier runs, where a core is spare.
        self._helper = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="route-ahead") if cores > 1 else None
        # With the card's held_labels, a thread that labels a step after its reply has gone, where
        # the route did not fit with its classifier, for the stream's steps after it.
        self._labeller = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="route-labels") \
            if cores > 1 and self.settings["held_labels"] else None
        # The route after the classifier in one compiled call where the card asks for nothing it
        # leaves out (deepcontact.faces.route_compiled): the dual solve, no damping, no
        # relabelling, no retries; the same numbers, without the NumPy calls between the pieces.
        self.compiled = (self.settings["solver"] == "dual" and self.settings["damping"] == 0
                         and self.settings["close"] is None and not self.settings["retry_pressing"])
        # What the route's first solve would import, not on a served step.
        import scipy.linalg  # noqa: F401
        import scipy.sparse.linalg  # noqa: F401

    def check_domain(self, domain: Domain) -> None:
        if self.fallback is not None:  # no grid here; a grid model served in its place may have one
            self.fallback.check_domain(domain)

    def warm_up(self, domain: Domain) -> float:
        return self.fallback.warm_up(domain) if self.fallback is not None else 0.0

    def predict(self, bodies, points, world, step, previous=None, friction=None, deadline=None,
                slowdown: float = 1.0, memory: dict | None = None,
                restitution: np.ndarray | None = None) -> Prediction:
        """As Predictor.predict; friction: (P,) each point's friction coefficient (the request's
        point_friction, required); deadline: time.perf_counter() s by which the answer is due
        (None: none), see fits; slowdown: how many times its own time a step's work is expected
        to take in wall time (the requests the server answers at once, over its cores); memory:
        a dict the server keeps for this stream and model between its steps (None: a step
        alone), where a card with carry keeps its admission's state (AdmissionCarry, by card
        name: a fallback route keeps its own); restitution: (P,) each point's (the request's
        point_restitution), or None: no point bounces. The route solves and checks the step with
        each point that closes faster than 1 m/s held at its bounce, as Box2D's solver holds it
        (deepcontact.faces.prepare_route), unless the card's `restitution` is false."""
        started, cpu = time.perf_counter(), time.thread_time()
        if not self.settings["restitution"]:
            restitution = None
        if len(points) == 0:
            return Prediction(np.zeros((0, 2), np.float32))
        if friction is None:
            raise ValueError(f"{self.name} needs each point's friction")
        lane = self._lanes if deadline is not None else None  # a step with a budget takes a free lane or none
        verdict = self.unfamiliar(bodies, points, friction, world)
        scaled = None
        if verdict is not None and self.settings["rescale"] and self.envelope is not None:
            # The step read at the scale the classifier was trained at: familiar there, it is
            # labelled so and solved in its own units (the reply still says it is unfamiliar).
            b, p, prev, physics, factors = self.envelope.rescaled(bodies, points, previous, world.physics)
            if factors != (1.0, 1.0, 1.0):
                scaled_world = World(world.domain, physics, world.tolerance)
                if self.unfamiliar(b, p, friction, scaled_world) is None:
                    scaled = (b, p, prev, scaled_world, factors[1] * factors[2])
        familiar = verdict is None or scaled is not None
        most = self.settings["max_points"]
        within = most is None or len(points) <= most
        held = memory.setdefault(f"{self.name}:held", HeldLabels()) \
            if self.settings["held_labels"] and memory is not None and familiar and within else None
        timely = self.fits(len(points), started, deadline, slowdown)
        answer, labelled = None, False
        if familiar and timely:
            if lane is None or lane.acquire(blocking=False):
                try:
                    answer = self._route(bodies, points, world, step, previous, friction, deadline, cpu, slowdown,
                                         scaled, memory, restitution, held=held)
                    labelled = True
                finally:
                    if lane is not None:
                        lane.release()
        elif held is not None and within:
            # Too large a step to label and solve in time: solved on the labels held for its
            # points, where each has some and the route ends in time without its classifier.
            fill = None
            if self.settings["held_from_builtin"]:  # a point new on the step: Box2D's start read as labels
                fill = face_labels(contact_face(points["builtin"], np.asarray(friction, np.float64)))
            labels = held.lookup(points, step, fill)
            if labels is not None and self.held_cost.fits(len(points), started, deadline, slowdown) \
                    and (lane is None or lane.acquire(blocking=False)):
                try:
                    answer = self._route(bodies, points, world, step, previous, friction, deadline, cpu, slowdown,
                                         scaled, memory, restitution, labels=labels)
                finally:
                    if lane is not None:
                        lane.release()
        if answer is None:
            # A world the classifier was not trained on, too large a step to solve, or to solve
            # in time, or every lane busy with another step's route: no labels asked for.
            answer = self._fallback(bodies, points, world, step, previous, friction, deadline, slowdown,
                                    memory=memory, restitution=restitution, scaled=scaled)
        if held is not None and not labelled and self._labeller is not None and slowdown <= 1.0:
            # Labelled on the spare core after the reply, for the stream's next steps.
            held.label_later(self._labeller, functools.partial(self._labels, bodies.copy(), points.copy(), world,
                                                               step, previous, friction, scaled), points, step)
        # The verdict goes with the answer: the reply says whether the step is familiar without
        # judging it again (the same envelope, about 15 us a step).
        return Prediction(answer.impulses, answer.stages, answer.served_by, verdict)

    def _labels(self, bodies, points, world, step, previous, friction, scaled=None) -> np.ndarray:
        """The classifier's answer (P, 2) on a step, as _route asks it (scaled: as _route's), its
        network's plain half alone: what server.held_labels holds."""
        asked = scaled if scaled is not None else (bodies, points, previous, world)
        return self.classifier.predict(asked[0], asked[1], asked[3], step, asked[2], friction=friction).impulses

    def _route(self, bodies, points, world, step, previous, friction, deadline, cpu: float,
               slowdown: float = 1.0, scaled=None, memory: dict | None = None, restitution=None,
               held: HeldLabels | None = None, labels: np.ndarray | None = None) -> Prediction:
        """predict's answer along the route (module docstring); cpu: the thread's CPU time when
        the step began; scaled: (bodies, points, previous, world, impulse factor) the classifier
        reads instead (the card's rescale: the step in the units it was trained in, and what its
        impulses are multiplied by to come back to the step's own), or None; held: where the classifier's answer is held for the
        stream's later steps (server.held_labels), or None; labels: (P, 2) labels held from an
        earlier step, solved on in place of the classifier's (its answer's served_by then ends
        in HELD), or None."""
        # The route's geometry (the frame, the admission's factorization) does not depend on the
        # labels: on a server with a core to spare it is built there while the classifier runs.
        # So does Box2D's start's side of the check against it (check_sweeps).
        ahead, mirror, prepared, builtin_change = None, {}, None, None
        free = self._helper is not None and slowdown <= 1.0
        checks = self.settings["against_builtin"] or scaled is not None
        sweeps = self._check_sweeps(len(points)) if checks else None
        stop = self._stop_tolerance(world)
        if labels is not None:
            pass  # held labels: no classifier to run beside the geometry
        elif isinstance(self.classifier, MirroredGraphPredictor):
            # The reflected half on the spare core while the step's half runs here, and the
            # geometry here after it, filling the wait. Without a free core the step's half
            # alone: in turn the reflection would add the network's time again to the step.
            later = _Later(_ahead, bodies, points, world.physics, friction, sweeps, stop, self._by_island(stop),
                           restitution) \
                if self.compiled and free else None
            mirror = {"spare": self._helper, "reflected": free, "meanwhile": later}
        elif self.compiled and free and len(points) >= AHEAD_POINTS:
            ahead = self._helper.submit(_ahead, bodies, points, world.physics, friction, sweeps, stop,
                                        self._by_island(stop), restitution)
        if labels is not None:  # held: no classifier, and nothing to build ahead while it runs
            guess = labels
            stages = {"features": 0.0, "inference": 0.0, "solve": 0.0, "admit": 0.0}
        else:
            asked = scaled if scaled is not None else (bodies, points, previous, world)
            answer = self.classifier.predict(asked[0], asked[1], asked[3], step, asked[2], friction=friction,
                                             **mirror)
            guess = answer.impulses
            if held is not None:
                held.keep(points, step, guess)
            stages = {"features": answer.stages["features"], "inference": answer.stages["inference"],
                      "solve": answer.stages["g2p"], "admit": 0.0}  # the network's output read as labels: the solve's
        if ahead is not None:
            prepared, builtin_change = ahead.result()
        elif mirror.get("meanwhile") is not None and mirror["meanwhile"].value is not None:
            prepared, builtin_change = mirror["meanwhile"].value
        carry = None
        if self.settings["carry"] and memory is not None:
            carry = (memory.setdefault(self.name, AdmissionCarry()), step)
        until = deadline
        if deadline is not None and self.settings["min_rounds"] is not None and checks:
            # Rounds past min_rounds only while the check after them would still end in time: its
            # sweeps are known where Box2D's side has run ahead, else at most both sides' in full.
            planned = self._route_sweeps(builtin_change, stop, len(points)) if builtin_change is not None \
                else 2 * (sweeps or 1)
            until = deadline - slowdown * planned * self.sweep_cost.estimate(len(points))
        impulses, extra_rounds = self._solved_on_labels(bodies, points, world, guess, friction, until,
                                                        stages, prepared, carry, restitution)
        served_by = None
        repaired, repairs_cpu = [], 0.0
        if impulses is not None and checks and self.settings["repairs"] and sweeps is not None \
                and self._by_island(stop):
            c0 = time.thread_time()
            repaired = self._repaired(bodies, points, world, impulses, friction, until, stages, prepared, restitution,
                                      slowdown * sweeps * self.sweep_cost.estimate(len(points)),
                                      stages["solve"] + stages["admit"])
            repairs_cpu = time.thread_time() - c0
        # A step read at another scale than its own is one the classifier was not trained on:
        # checked as the card's against_builtin checks every step.
        if impulses is not None and checks:
            t0 = time.perf_counter()
            counted = 0
            if sweeps is not None and builtin_change is None:  # Box2D's side here, not run ahead
                builtin_change = _sweep_change(bodies, points, points["builtin"], np.asarray(friction, np.float64),
                                               world.physics, sweeps, prepared, stop, self._by_island(stop),
                                               restitution=restitution)
                counted = min(builtin_change[0], sweeps)
            counted += (1 + len(repaired)) * self._route_sweeps(builtin_change, stop, len(points))
            if repaired:  # each island from whichever of the route's answers stops it soonest, or Box2D's
                c0 = time.thread_time()
                impulses, taken = self._soonest_by_island(bodies, points, [impulses, *repaired], friction, world,
                                                          prepared, builtin_change, restitution)
                repairs_cpu += (time.thread_time() - c0) * len(repaired) / (1 + len(repaired))
            else:
                taken = np.broadcast_to(np.asarray(self._beats_builtin(bodies, points, impulses, friction, world,
                                                                       prepared, builtin_change, restitution), bool),
                                        (len(points),))
            if not taken.any():
                impulses, served_by = points["builtin"].copy(), BUILTIN
            elif not taken.all():  # the route's answer on the islands it stops sooner, Box2D's on the rest
                impulses = np.where(taken[:, None], impulses, points["builtin"])
            checked = time.perf_counter() - t0
            stages["admit"] += checked
            self.sweep_cost.observe(len(points), checked / counted)
        if impulses is None:  # labels the limits would not let the solve meet
            # Not a second route after this one: on the thesis world it would double a fifth of
            # the steps' cost (round trip p99 5.5 ms against 2.3) for 0.7 % of the iterations.
            fallback = self._fallback(bodies, points, world, step, previous, friction, deadline, slowdown,
                                      second_route=False, scaled=scaled)
            impulses, served_by = fallback.impulses, fallback.served_by
            for name, seconds in fallback.stages.items():
                stages[name] = stages.get(name, 0.0) + seconds
        # The route's CPU time, not the wait for its geometry built ahead: counted, that wait (the
        # other core busy with a simulation beside the server) turned away more of the Pyramid's
        # large steps than the replies past the deadline it spared (0.930x against 0.858x of
        # Builtin's iterations, 2 against 8 of 2,581 replies late; docs/research/2026-12-07-fewer-
        # rounds-rather-than-none.md); the service's margin is there for it. Nor the repairs and
        # their share of the check: each begins only where it still ends in time, so a step the
        # route fits without them is not turned away for them.
        (self.cost if labels is None else self.held_cost).observe(len(points),
                                                                  time.thread_time() - cpu - extra_rounds - repairs_cpu)
        if labels is not None and served_by is None:
            served_by = f"{self.name}{HELD}"
        if self.gate is not None:
            t0 = time.perf_counter()
            if not self.gate.serves_model(step_features(bodies, points, impulses)):
                impulses = points["builtin"].copy()  # Box2D's own warm start: the gate expects the route to lose here
            stages["admit"] += time.perf_counter() - t0
        return Prediction(np.asarray(impulses).astype(np.float32, copy=False), stages, served_by)

    def _repaired(self, bodies, points, world, impulses, friction, until, stages: dict[str, float], prepared,
                  restitution, check_seconds: float, route_seconds: float) -> list[np.ndarray]:
        """The route's answer repaired in turn, up to the card's `repairs` times: [(P, 2) N s], each
        the step solved and admitted on the labels one step of an active-set method reads off the
        answer before it (deepcontact.faces.repair_face, each point's bounce held), where those
        labels differ from the ones before, each admitted in the card's repair_rounds (its rounds
        where null). By `until` (perf_counter() s, or None) the k-th repair
        leaves time for the check's sweeps from k more starts (check_seconds each): none is begun
        that would not end by then, taking as long as the solve before it (route_seconds, the
        route's own, for the first), and its admission rounds end there. Their seconds go to
        stages["solve"] and ["admit"].

        Why: a classifier that labels a falling or sliding point open or sticking leaves it closing
        or pushed along by its friction, which the solve on those labels then shows; on the zoo's
        stacks and terrain, read so once or twice, the step's own face comes back, where on piles at
        rest the labels it reads are seldom better, so the check picks between them island by
        island (docs/research/2026-12-08-repaired-labels.md)."""
        face, mu = self.settings, np.asarray(friction, np.float64)
        out, labels_before, expected = [], None, route_seconds
        for k in range(1, face["repairs"] + 1):
            t0 = time.perf_counter()
            cut = None if until is None else until - k * check_seconds
            if cut is not None and t0 + expected >= cut:
                break
            labels = repair_face(bodies, points, impulses, mu, world.physics, restitution=restitution)
            if labels_before is not None and np.array_equal(labels, labels_before):
                break
            labels_before = labels
            answer = route_compiled(bodies, points, face_labels(labels), mu, world.physics, face["pressing"],
                                    face["share"], LABELS_FRICTION, face["repair_rounds"] or face["rounds"], cut,
                                    prepared, face["relax"],
                                    face["rho"], None, slide_in_bodies=face["slide_in_bodies"],
                                    restitution=restitution)
            expected = time.perf_counter() - t0
            if answer is None:
                break
            stages["solve"] += answer.solve_seconds
            stages["admit"] += answer.admit_seconds
            if face["max_residual"] is not None and answer.residual > face["max_residual"]:
                break
            impulses = answer.impulses
            out.append(impulses)
        return out

    def _soonest_by_island(self, bodies, points, answers: list[np.ndarray], friction, world, prepared,
                           builtin_change: tuple, restitution) -> tuple[np.ndarray, np.ndarray]:
        """(impulses (P, 2) N s, taken (P,) bool): each island of the step from the start among
        Box2D's (the request's builtin) and `answers` ([(P, 2) N s], the route's, then its repairs)
        that stops it soonest on the server's copy of the step, by the smaller last change where
        two stop at the same sweep (Box2D's first, then the answers in order, on a tie); taken
        where that is not Box2D's. builtin_change: _sweep_change's by island, Box2D's side."""
        stop = self._stop_tolerance(world)
        box2d = builtin_change[2]
        routes = island_sweeps_to_stop(bodies, points, np.asarray(answers, np.float64),
                                       np.asarray(friction, np.float64), world.physics, stop,
                                       self._route_sweeps(builtin_change, stop, len(points)), prepared,
                                       restitution=restitution)[2]
        counts = np.concatenate([box2d.counts, routes.counts])
        changes = np.concatenate([box2d.changes, routes.changes])
        chosen = np.lexsort((changes, counts), axis=0)[0][box2d.point]  # (P,): 0 Box2D's, k the k-th answer
        starts = np.concatenate([np.asarray(points["builtin"], np.float64)[None], np.asarray(answers, np.float64)])
        return starts[chosen, np.arange(len(points))], chosen > 0

    def _stop_tolerance(self, world: World) -> float:
        """The client's stopping rule (N s) where the card's check counts the sweeps to it
        (check_stop) and the client declared it; else 0, the check by the changes at sweep N."""
        return world.tolerance if self.settings["check_stop"] and world.tolerance > 0 else 0.0

    def _by_island(self, stop: float) -> bool:
        """Whether the check counts each island on its own (the card's by_island, where the check
        counts sweeps to the client's stopping rule `stop` > 0 N s)."""
        return self.settings["by_island"] and stop > 0

    def _beats_builtin(self, bodies, points, impulses, friction, world, prepared=None,
                       builtin_change: tuple | None = None, restitution=None) -> bool | np.ndarray:
        """Whether one projected Jacobi step from the route's answer ((P, 2) N s) would change the
        impulses less than one from Box2D's warm start (the request's builtin): the card's
        against_builtin; with its check_sweeps N, whether the solver's N-th sweep from it would
        (deepcontact.faces.sweep_changes; prepared: prepare_route's geometry, or None;
        builtin_change: Box2D's start's side, (sweeps to the stopping rule, change), where _ahead
        has priced it); with check_stop and the client's stopping rule, whether it stops in fewer
        sweeps than Box2D's start, by the last sweep's changes where both stop at the same sweep
        or neither by sweep N. On worlds the classifier was not trained on, labels it reads as right
        can still leave the solver further from its end than Box2D's start, which at rest is
        nearly there (at a time step of 1/30 s the zoo route alone cost 1.42x Builtin's
        iterations on Builtin's states of 850-854; checked so, 0.97x). With the card's by_island (and
        Box2D's side priced so, builtin_change's third item faces.Islands), whether it does so on
        each point's island: (P,) bool, the route's answer served there and Box2D's start elsewhere
        (Box2D's solver stops each island at its own sweep). restitution: as predict's, where
        prepared is None."""
        mu = np.asarray(friction, np.float64)
        sweeps = self._check_sweeps(len(points))
        if sweeps is not None:
            stop = self._stop_tolerance(world)
            if builtin_change is None:
                builtin_change = _sweep_change(bodies, points, points["builtin"], mu, world.physics, sweeps, prepared,
                                               stop, self._by_island(stop), restitution=restitution)
            if len(builtin_change) > 2:
                box2d = builtin_change[2]
                route = island_sweeps_to_stop(bodies, points, np.asarray(impulses, np.float64)[None], mu, world.physics,
                                              stop, self._route_sweeps(builtin_change, stop, len(points)), prepared,
                                              restitution=restitution)[2]
                wins = (route.counts[0] < box2d.counts[0]) | (
                    (route.counts[0] == box2d.counts[0]) & (route.changes[0] < box2d.changes[0]))
                return wins[box2d.point]
            box2d_sweeps, box2d = builtin_change[:2]
            route_sweeps, route = _sweep_change(bodies, points, impulses, mu, world.physics,
                                                self._route_sweeps(builtin_change, stop, len(points)), prepared, stop,
                                                restitution=restitution)
            if route_sweeps == box2d_sweeps:  # both stop at the same sweep, or neither by sweep N
                return route < box2d
            return route_sweeps < box2d_sweeps
        masses = effective_masses(bodies, points)
        route = jacobi_change(bodies, points, impulses, mu, world.physics, masses)
        return route < jacobi_change(bodies, points, points["builtin"], mu, world.physics, masses)

    def _check_sweeps(self, n_points: int) -> int | None:
        """The sweeps the check plays from each start on a step of n_points points: the card's
        check_sweeps, and with its check_work no more than check_work / n_points (at least
        one), so that a large step's check costs no more than a smaller one's: on Box2D's
        Pyramid, where neither start stops within 200 sweeps, 200 of them from each start were
        about 8 ms of a 700-point step and the route fitted the 10 ms deadline on few of them.
        None: no check by sweeps."""
        sweeps, work = self.settings["check_sweeps"], self.settings["check_work"]
        if sweeps is None or work is None or n_points == 0:
            return sweeps
        return max(1, min(sweeps, work // n_points))

    def _route_sweeps(self, builtin_change: tuple[int, float] | None, stop: float, n_points: int) -> int:
        """The sweeps the check plays from the route's answer on a step of n_points points (1 for
        the Jacobi check, which has none): _check_sweeps's, but by the stopping rule (stop > 0
        N s) none past the sweep where Box2D's start stopped (builtin_change[0]): stopped by
        then, its count and last change are the same; not, it has lost either way (its count
        then one more than Box2D's). On a step the route loses that spares up to check_sweeps
        of them."""
        sweeps = self._check_sweeps(n_points)
        if sweeps is None:
            return 1
        return max(1, min(sweeps, builtin_change[0])) if stop > 0 else sweeps

    def fits(self, n_points: int, now: float, deadline: float | None, slowdown: float = 1.0) -> bool:
        """Whether the route serves a step of n_points points begun at `now`: not past the
        card's max_points, and, with a deadline (perf_counter() s), expected to end by it
        (cost: the route's cost at each size, learned on this host, times the slowdown). Where
        it does not, the fallback answers, in a fraction of the time: the client gets the next
        best answer in time rather than the best one too late (and then Box2D's own start)."""
        most = self.settings["max_points"]
        if most is not None and n_points > most:
            return False
        return self.cost.fits(n_points, now, deadline, slowdown)

    def _solved_on_labels(self, bodies, points, world, labels, friction, deadline,
                          stages: dict[str, float], prepared=None, carry=None,
                          restitution=None) -> tuple[np.ndarray | None, float]:
        """(impulses, extra): impulses (P, 2) N s, the route's answer: the classifier's answer
        (labels, (P, 2) N s) read as each point's label, the step solved on them and admitted
        (deepcontact.faces, as solved_on_labels); where the admitted solve misses its labels by
        more than max_residual, the labels read again at each of retry_pressing's thresholds in
        turn. None where no reading meets it. extra: the seconds its admission spent past the
        card's min_rounds rounds (0 without min_rounds). friction: (P,) each point's friction coefficient;
        deadline: perf_counter() s after which no admission round begins (a route begun late
        answers with what it has rather than miss), and no retry. Adds each reading's seconds
        to stages["solve"] and stages["admit"]. carry: (AdmissionCarry, step) where the card's
        carry keeps the admission's state along the stream (the compiled route only), or None."""
        face = self.settings
        if self.compiled:
            args = carry[0].begin(points, carry[1]) if carry is not None else None
            answer = route_compiled(bodies, points, labels, friction, world.physics, face["pressing"], face["share"],
                                    face["label_friction"], face["rounds"], deadline, prepared, face["relax"],
                                    face["rho"], args, slide_in_bodies=face["slide_in_bodies"],
                                    restitution=restitution)
            if carry is not None:
                if answer is not None:
                    carry[0].keep(points, carry[1], args)
                else:
                    carry[0].forget()
            if answer is not None:
                stages["solve"] += answer.solve_seconds
                stages["admit"] += answer.admit_seconds
                extra = 0.0
                if face["min_rounds"] is not None and answer.rounds_run > face["min_rounds"]:
                    extra = answer.admit_seconds * (answer.rounds_run - face["min_rounds"]) / answer.rounds_run
                served = face["max_residual"] is None or answer.residual <= face["max_residual"]
                return (answer.impulses if served else None), extra
            if face["max_residual"] is not None:
                # The compiled dual declined the labels' system, far from consistent: labels that
                # are not this step's. Solved by least squares piece by piece (3 ms at 160 points),
                # 10 of 11 such steps of seeds 900-903 then missed max_residual: the fallback at once.
                return None, 0.0
            # Without max_residual every reading is served: the route piece by piece, whose least
            # squares answers it.
        t0 = time.perf_counter()
        frame = contact_frame(bodies, points)  # its factorizations are kept on it, for every reading
        labels, mu = labels.astype(np.float64), np.asarray(friction, np.float64)
        for k, pressing in enumerate([face["pressing"], *face["retry_pressing"]]):
            if k and deadline is not None and time.perf_counter() >= deadline:
                break
            read, solved = read_and_solve(bodies, points, labels, mu, world.physics, pressing, face["share"],
                                          face["label_friction"], frame, face["damping"], face["solver"],
                                          face["close"], restitution)
            t1 = time.perf_counter()
            impulses, residual = admit_solved(bodies, points, read, solved, mu, world.physics, face["rounds"], frame,
                                              deadline, face["relax"], face["rho"], restitution)
            t2 = time.perf_counter()
            stages["solve"] += t1 - t0
            stages["admit"] += t2 - t1
            t0 = t2
            if face["max_residual"] is None or residual <= face["max_residual"]:
                return impulses, 0.0
        return None, 0.0

    def unfamiliar(self, bodies, points, friction, world) -> str | None:
        """Why the step lies outside what the classifier was trained on (the card's trained_on;
        joints not judged), or None where it lies inside (and everywhere for a card without one:
        it labels every world)."""
        return None if self.envelope is None else self.envelope.unfamiliar(bodies, points, friction, world.physics, None)

    def _fallback_knows(self, bodies, points, friction, world) -> bool:
        """Whether the step lies inside the fallback card's training envelope (its trained_on;
        a card without one is served everywhere). A network trained on one kind of world can
        cost several times Box2D's iterations on another (a pile of discs' fallback on a
        pyramid of boxes, docs/research/2026-12-06-a-zoo-of-worlds.md): outside it, Box2D's."""
        envelope = self.fallback.envelope
        return envelope is None or envelope.unfamiliar(bodies, points, friction, world.physics, None) is None

    def _fallback(self, bodies, points, world, step, previous, friction, deadline=None,
                  slowdown: float = 1.0, second_route: bool = True, memory: dict | None = None,
                  restitution=None, scaled=None) -> Prediction:
        """The answer where the route is not served: the fallback card's where the step lies in
        what it was trained on, else Box2D's warm start (the request's builtin impulses), with
        served_by naming it. With a deadline, Box2D's
        also where the fallback (not itself a route, which judges that alone) is not expected to
        end by it either (a server answering more
        requests at once than its cores keep up with): an answer in time that the client would
        have used anyway, rather than a better one it cannot wait for. Where the fallback is
        another route and second_route is False (this one's route has run), that route's own
        fallback answers instead. scaled: the step rescaled as _route's is, or None; a fallback
        network that does not know the step but knows it so is asked so, its answer brought back
        to the step's units (a network trained at one scale, as the graph fallback is at the
        thesis world's, then serves the same world in other units)."""
        if not second_route and isinstance(self.fallback, FaceRoutePredictor):
            return self.fallback._fallback(bodies, points, world, step, previous, friction, deadline, slowdown,
                                           second_route=False, scaled=scaled)
        now = time.perf_counter()
        # A fallback that keeps to the deadline itself (another route) judges its own cost: it
        # knows how few rounds it can end in (its min_rounds), where its whole cost seen from
        # here would turn away every step its full rounds would not end.
        judged = getattr(self.fallback, "takes_deadline", False)
        asked, factor = (bodies, points, previous, world), 1.0
        if self.fallback is not None and not self._fallback_knows(bodies, points, friction, world):
            if scaled is not None and not isinstance(self.fallback, FaceRoutePredictor) \
                    and self._fallback_knows(scaled[0], scaled[1], friction, scaled[3]):
                asked, factor = scaled[:4], scaled[4]
            else:
                asked = None
        if self.fallback is None or asked is None \
                or not (judged or self.fallback_cost.fits(len(points), now, deadline, slowdown)):
            return Prediction(points["builtin"].astype(np.float32), served_by=BUILTIN)
        extra = {"friction": friction} if "point_friction" in self.fallback.requires else {}
        if getattr(self.fallback, "takes_deadline", False):  # another route: it keeps to the same deadline
            extra.update(deadline=deadline, slowdown=slowdown)
        if getattr(self.fallback, "takes_memory", False):
            extra["memory"] = memory
        if isinstance(self.fallback, FaceRoutePredictor):  # another route: the same bounces
            extra["restitution"] = restitution
        cpu = time.thread_time()
        answer = self.fallback.predict(asked[0], asked[1], asked[3], step, asked[2], **extra)
        self.fallback_cost.observe(len(points), time.thread_time() - cpu)
        impulses = answer.impulses if factor == 1.0 else (answer.impulses * np.float32(factor)).astype(np.float32)
        # A route's own fallback, where it answered, is named rather than the route.
        return Prediction(impulses, answer.stages, answer.served_by or self.fallback.name)


def _ahead(bodies, points, physics, friction, sweeps: int | None, stop: float = 0.0, by_island: bool = False,
           restitution=None):
    """(prepare_route's geometry, Box2D's start's side of the check by sweeps as _sweep_change
    gives it, or None where there is no such check): a step's work that does not wait on its labels."""
    prepared = prepare_route(bodies, points, physics, restitution)
    if sweeps is None:
        return prepared, None
    return prepared, _sweep_change(bodies, points, points["builtin"], friction, physics, sweeps, prepared, stop,
                                   by_island, restitution=restitution)


def _sweep_change(bodies, points, start, friction, physics, sweeps: int, prepared=None,
                  stop: float = 0.0, by_island: bool = False, restitution=None) -> tuple:
    """(sweeps run, the last one's change N s) from one start (P, 2) N s: with a stopping rule
    `stop` > 0 (N s) deepcontact.faces.sweeps_to_stop's (sweeps + 1 where it does not stop by
    then), else (sweeps + 1, faces.sweep_changes's change at sweep `sweeps`). by_island (with
    `stop`): island_sweeps_to_stop's, and its faces.Islands third. restitution: as prepare_route's,
    where prepared is None."""
    start = np.asarray(start, np.float64)[None]
    if stop > 0 and by_island:
        counts, changes, islands = island_sweeps_to_stop(bodies, points, start, friction, physics, stop, sweeps,
                                                         prepared, restitution=restitution)
        return int(counts[0]), float(changes[0]), islands
    if stop > 0:
        counts, changes = sweeps_to_stop(bodies, points, start, friction, physics, stop, sweeps, prepared,
                                         restitution=restitution)
        return int(counts[0]), float(changes[0])
    return sweeps + 1, float(sweep_changes(bodies, points, start, friction, physics, sweeps, prepared,
                                           restitution)[0])


class _Later:
    """fn(*args), run when called (by whoever has the time), its value kept: None until then."""

    def __init__(self, fn, *args):
        self.fn, self.args, self.value = fn, args, None

    def __call__(self) -> None:
        self.value = self.fn(*self.args)
