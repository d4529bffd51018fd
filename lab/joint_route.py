"""`deepcontact lab joint-route`: would the face route pay on worlds with joints if the joints
entered its contact problem?

    deepcontact lab joint-route --world simclient.zoo:ragdolls --seeds 850-853

The shipped route answers Box2D's own warm start at every point that touches a jointed body
(server/joints.py): the network's labels were learned on free bodies and the route's system has
no joint in it. This instrument adds the joints to the step's problem, dense and in NumPy, and
prices each answer by the engine's trial solves on Box2D's own trajectory (the same states for
every answer):

    builtin        Box2D's warm start
    served         what the server answers now: the default's answer around the joints
    oracle         the step solved to convergence from Box2D's start (Engine.oracle, joints in
                   it): the best a warm start of the contact points alone can be
    labels:oracle  the oracle's own labels (contact_face), the step solved on them with every
                   joint's rows as equations, admitted into the cones
    labels:zoo     the zoo classifier's labels (models/zoo.json's network, read with its card's
                   settings), solved and admitted the same way
    labels:zoo-free the same labels solved as the shipped route would without its decline:
                   the joints left out of the problem
    labels:oracle-route  the oracle's labels through the shipped route's own solve and
                   admission (deepcontact.faces.solved_on_labels): the joints left out
    labels:builtin Box2D's start read as labels (contact_face at the oracle's thresholds: the step
                   before's converged impulses at the points it shares with this one), solved with
                   the joints' rows and admitted the same way
    labels:builtin-route  the same labels through the shipped route's own solve and admission
                   (the joints left out)
    *-near-builtin the same solve, its unknowns taken nearest Box2D's start rather than least
                   norm (which of a redundant problem's solutions)

A joint enters as the rows Box2D's joint solver holds at zero relative velocity: a revolute
joint's point (two rows), a weld's point and angle (three, rigid welds only), a prismatic
joint's perpendicular and angle (two), a rigid distance joint's axis (one), a wheel joint's
perpendicular (one); a motor's row holds its speed, its impulse within the motor's most (a
motor at rest is joint friction); a limit's row enters where Box2D's solver would hold it this
step (at or past it), pushing one way. Springs (a wheel joint's, a soft weld's or distance
joint's) are not rows: Box2D's solver applies them from its own start. Every row is an
equation of the solve; the admission is the nearest impulses in the cones (open points held at
0, each joint row's impulse within its bounds) that move every body as the solve does, by ADMM
on the dense system (`--rounds`).

A research instrument: a Python loop over joints and dense algebra, minutes a world.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from bench.stats import ratio_interval
from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, contact_face
from deepcontact.kinematics import bounce, contact_jacobian

ANSWERS = ("builtin", "served", "oracle", "labels:oracle", "labels:oracle-route", "labels:oracle-near-builtin", "labels:zoo",
           "labels:zoo-near-builtin", "labels:zoo-free", "labels:builtin", "labels:builtin-route")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION", help="a world with joints")
    parser.add_argument("--seeds", default="850-853", help="seeds (default 850-853, choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--rounds", type=int, default=200, help="admission rounds (default 200)")
    parser.add_argument("--models", default="models", help="model folder (default models/)")


def joint_rows(engine, bodies: np.ndarray) -> dict[str, np.ndarray]:
    """The joints' rows: a, b (R,) body indices; ja, jb (R, 3) such that a row's relative
    velocity is ja . (vx, vy, w)_a + jb . (vx, vy, w)_b (m/s or rad/s); lo, hi (R,) the bounds
    of its impulse (N s or N m s; +-inf for an equality); speed (R,) the velocity it holds (a
    motor's). A limit enters where Box2D's solver would hold it this step (at or past it)."""
    import Box2D

    pairs = engine.joints()  # (J, 2) engine body indices, in the world's joint order
    joints = list(engine.world.joints)
    centres = bodies["position"].astype(np.float64)

    def at(body, k) -> bool:
        return np.allclose(np.array(body.worldCenter), centres[k], atol=1e-4)

    if joints and not all(at(j.bodyA, a) and at(j.bodyB, b) for j, (a, b) in zip(joints, pairs)):
        joints = joints[::-1]
        if not all(at(j.bodyA, a) and at(j.bodyB, b) for j, (a, b) in zip(joints, pairs)):
            raise RuntimeError("pybox2d's joints and the engine's export disagree")
    a_rows, b_rows, ja, jb, lo, hi, speed = [], [], [], [], [], [], []
    dt = engine.config.dt

    def cross(r, v):  # z of r x v
        return r[0] * v[1] - r[1] * v[0]

    def add(a, b, ra, rb, d, ang=False, bounds=(-np.inf, np.inf), target=0.0):
        """A row: d . (vB + wB x rB - vA - wA x rA), or wB - wA where ang, held at target
        (m/s or rad/s) by an impulse within bounds (N s or N m s)."""
        if ang:
            ja.append((0.0, 0.0, -1.0)), jb.append((0.0, 0.0, 1.0))
        else:
            ja.append((-d[0], -d[1], -cross(ra, d))), jb.append((d[0], d[1], cross(rb, d)))
        a_rows.append(a), b_rows.append(b), lo.append(bounds[0]), hi.append(bounds[1]), speed.append(target)

    slop = 2.0 / 180.0 * np.pi  # b2_angularSlop
    for joint, (a, b) in zip(joints, pairs):
        pa, pb = np.array(joint.bodyA.worldCenter), np.array(joint.bodyB.worldCenter)
        ra, rb = np.array(joint.anchorA) - pa, np.array(joint.anchorB) - pb
        if isinstance(joint, (Box2D.b2RevoluteJoint, Box2D.b2WeldJoint)):
            add(a, b, ra, rb, (1.0, 0.0)), add(a, b, ra, rb, (0.0, 1.0))
            if isinstance(joint, Box2D.b2WeldJoint) and joint.GetFrequency() == 0:
                add(a, b, ra, rb, None, ang=True)
            if isinstance(joint, Box2D.b2RevoluteJoint):
                if joint.motorEnabled:
                    most = joint.GetMaxMotorTorque() * dt
                    add(a, b, ra, rb, None, ang=True, bounds=(-most, most), target=joint.motorSpeed)
                if joint.limitEnabled:
                    angle, (lower, upper) = joint.angle, joint.limits
                    if abs(upper - lower) < 2 * slop:
                        add(a, b, ra, rb, None, ang=True)
                    elif angle <= lower:
                        add(a, b, ra, rb, None, ang=True, bounds=(0.0, np.inf))
                    elif angle >= upper:
                        add(a, b, ra, rb, None, ang=True, bounds=(-np.inf, 0.0))
        elif isinstance(joint, (Box2D.b2PrismaticJoint, Box2D.b2WheelJoint)):
            axis = np.array(joint.bodyA.GetWorldVector(joint.GetLocalAxisA()))
            perp = np.array((-axis[1], axis[0]))
            # Box2D's rows take body A's lever to B's anchor (d + rA).
            d = np.array(joint.anchorB) - np.array(joint.anchorA)
            add(a, b, ra + d, rb, perp)
            if isinstance(joint, Box2D.b2PrismaticJoint):
                add(a, b, ra, rb, None, ang=True)
                if joint.motorEnabled:
                    most = joint.maxMotorForce * dt
                    add(a, b, ra + d, rb, axis, bounds=(-most, most), target=joint.motorSpeed)
                if joint.limitEnabled:
                    t, (lower, upper) = joint.translation, joint.limits
                    if abs(upper - lower) < 2 * 0.005:
                        add(a, b, ra + d, rb, axis)
                    elif t <= lower:
                        add(a, b, ra + d, rb, axis, bounds=(0.0, np.inf))
                    elif t >= upper:
                        add(a, b, ra + d, rb, axis, bounds=(-np.inf, 0.0))
            elif joint.motorEnabled:
                most = joint.maxMotorTorque * dt
                add(a, b, ra, rb, None, ang=True, bounds=(-most, most), target=joint.motorSpeed)
        elif isinstance(joint, Box2D.b2DistanceJoint) and joint.frequency == 0:
            u = np.array(joint.anchorB) - np.array(joint.anchorA)
            if np.hypot(*u) > 1e-6:
                add(a, b, ra, rb, u / np.hypot(*u))
    return {"a": np.array(a_rows, int), "b": np.array(b_rows, int), "ja": np.array(ja, float).reshape(-1, 3),
            "jb": np.array(jb, float).reshape(-1, 3), "lo": np.array(lo, float), "hi": np.array(hi, float),
            "speed": np.array(speed, float)}


class Problem:
    """One step's velocity problem, dense: the contacts' J (2P, 3D), the joints' (R, 3D), M^-1
    (3D,), and the velocities after gravity (3D,), over the D dynamic bodies; restitution (P,)
    each point's, or None: where a point closes faster than 1 m/s before any impulse its normal
    row holds the bounce Box2D holds it at (restitution times that speed), else rest."""

    def __init__(self, bodies, points, joints, gravity, dt, restitution=None):
        dyn = bodies["type"] == 2
        self.row = np.full(len(bodies), -1)
        self.row[dyn] = np.arange(int(dyn.sum()))
        D = int(dyn.sum())
        self.jc = contact_jacobian(bodies, points).T  # (2P, 3D)
        a, b, ja, jb = joints["a"], joints["b"], joints["ja"], joints["jb"]
        self.lo, self.hi, self.speed = joints["lo"], joints["hi"], joints["speed"]
        self.jj = np.zeros((len(a), 3 * D))
        for body, j in ((a, ja), (b, jb)):
            on = self.row[body] >= 0
            for c in range(3):
                np.add.at(self.jj, (np.flatnonzero(on), 3 * self.row[body[on]] + c), j[on, c])
        m = bodies["mass"][dyn].astype(np.float64)
        inertia = bodies["inertia"][dyn].astype(np.float64)
        self.minv = np.stack([1 / m, 1 / m, np.where(inertia > 0, 1 / np.maximum(inertia, 1e-30), 0.0)], 1).ravel()
        v = np.stack([bodies["velocity"][dyn, 0] + dt * gravity[0], bodies["velocity"][dyn, 1] + dt * gravity[1],
                      bodies["angular_velocity"][dyn]], 1).astype(np.float64)
        self.v0 = v.ravel()
        self.bias = bounce((self.jc @ self.v0)[0::2], restitution)  # (P,) m/s, what each normal row holds

    def solve(self, face: np.ndarray, mu: np.ndarray, with_joints: bool = True,
              reference: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(contact impulses (P, 2) N s, joint impulses (R,)): the step solved on `face`, the
        joints' rows as equations (with_joints), least norm."""
        P = len(face)
        press = np.flatnonzero(face != OPEN)
        stick = np.flatnonzero(face == STICKS)
        sign = np.where(face == SLIDES_PLUS, 1.0, np.where(face == SLIDES_MINUS, -1.0, 0.0))
        cols = [self.jc[2 * press] + (sign[press] * mu[press])[:, None] * self.jc[2 * press + 1], self.jc[2 * stick + 1]]
        eqs = [self.jc[2 * press], self.jc[2 * stick + 1]]
        R = len(self.jj) if with_joints else 0
        if R:
            cols.append(self.jj), eqs.append(self.jj)
        C, E = np.vstack(cols), np.vstack(eqs)  # (n, 3D), (m, 3D)
        A = (E * self.minv) @ C.T
        rhs = -E @ self.v0
        rhs[:len(press)] += self.bias[press]
        if R:
            rhs[len(rhs) - R:] += self.speed
        x0 = np.zeros(A.shape[1])
        if reference is not None:  # the solution nearest it (its unknowns' values), not the least-norm one
            x0[:len(press)] = reference[press, 0]
            x0[len(press):len(press) + len(stick)] = reference[stick, 1]
        x = x0 + np.linalg.lstsq(A, rhs - A @ x0, rcond=1e-10)[0]
        out = np.zeros((P, 2))
        out[press, 0] = x[:len(press)]
        out[press, 1] = sign[press] * mu[press] * x[:len(press)]
        out[stick, 1] = x[len(press):len(press) + len(stick)]
        return out, x[len(press) + len(stick):] if R else np.zeros(len(self.jj))

    def admit(self, contact: np.ndarray, joint: np.ndarray, face: np.ndarray, mu: np.ndarray, rounds: int,
              with_joints: bool = True) -> np.ndarray:
        """(P, 2) N s: the impulses nearest (contact, joint) that lie in every cone (open points 0,
        the joints' free) and give the bodies the same impulse, by ADMM."""
        P = len(contact)
        G = np.hstack([self.jc.T, self.jj.T]) if with_joints and len(self.jj) else self.jc.T  # (3D, n)
        x0 = np.concatenate([contact.ravel(), joint if G.shape[1] > 2 * P else np.zeros(0)])
        pinv = np.linalg.pinv(G @ G.T, rcond=1e-12)
        held = face == OPEN

        def affine(y):
            return y - G.T @ (pinv @ (G @ (y - x0)))

        def cones(y):
            z = y.copy()
            c = z[:2 * P].reshape(P, 2)
            n, t = c[:, 0].copy(), c[:, 1].copy()
            m = mu
            inside = np.abs(t) <= m * n
            polar = m * np.abs(t) <= -n
            edge = ~inside & ~polar
            s = (n + m * np.abs(t)) / (1 + m * m)
            c[:, 0] = np.where(inside, n, np.where(polar, 0.0, s))
            c[:, 1] = np.where(inside, t, np.where(polar, 0.0, np.sign(t) * m * s))
            c[held] = 0.0
            if len(z) > 2 * P:
                z[2 * P:] = np.clip(z[2 * P:], self.lo, self.hi)
            return z

        z, u = cones(x0), np.zeros_like(x0)
        for _ in range(rounds):
            x = affine(z - u)
            z = cones(x + u)
            u += x - z
        return z[:2 * P].reshape(P, 2)


def price(spec, seed: int, models: str, rounds: int) -> dict[str, np.ndarray]:
    """{answer: (steps,) velocity iterations} on Box2D's trajectory of (spec, seed)."""
    from pathlib import Path

    from bench.inprocess import declared_world
    from server.joints import predict_around_joints
    from server.predictors import load_model
    from simclient import worlds

    engine = worlds.build(spec, seed)
    world = declared_world(spec, engine)
    default = load_model(Path(models) / "default.json")
    zoo = load_model(Path(models) / "zoo.json")
    face = zoo.settings
    out = {k: [] for k in ANSWERS}
    previous = None
    g, dt = world.physics.gravity, engine.config.dt
    for k in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points) == 0 or not engine.awake()[np.concatenate([points["body_a"], points["body_b"]])].any():
            engine.solve()
            continue
        mu = points["friction"].astype(np.float64)
        builtin = engine.builtin_start()
        out["builtin"].append(engine.trial(*builtin))
        jrows = engine.joints()
        answer = predict_around_joints(default, bodies, points, jrows, world, k, previous,
                                       friction=points["friction"].astype(np.float32))
        imp = np.ascontiguousarray(answer.impulses, np.float32)
        out["served"].append(engine.trial(np.ascontiguousarray(imp[:, 0]), np.ascontiguousarray(imp[:, 1])))
        oracle = engine.oracle(start=builtin)
        oracle = np.where(np.isfinite(oracle), oracle, np.stack(builtin, 1))  # points no awake island solves
        out["oracle"].append(engine.trial(np.ascontiguousarray(oracle[:, 0]), np.ascontiguousarray(oracle[:, 1])))
        problem = Problem(bodies, points, joint_rows(engine, bodies), g, dt)
        labels = zoo.classifier.predict(bodies, points, world, k, previous,
                                        friction=points["friction"].astype(np.float32)).impulses
        read_at = mu if face["label_friction"] is None else np.full(len(points), float(face["label_friction"]))
        faces = {"labels:oracle": contact_face(oracle.astype(np.float64), mu),
                 "labels:zoo": contact_face(labels.astype(np.float64), read_at, face["pressing"], face["share"]),
                 "labels:builtin": contact_face(np.stack(builtin, 1).astype(np.float64), mu)}
        faces["labels:zoo-free"] = faces["labels:zoo"]
        faces["labels:oracle-near-builtin"] = faces["labels:oracle"]
        faces["labels:zoo-near-builtin"] = faces["labels:zoo"]
        start = np.stack(builtin, 1).astype(np.float64)
        for name, f in faces.items():
            joined = name != "labels:zoo-free"
            contact, joint = problem.solve(f, mu, joined, start if name.endswith("near-builtin") else None)
            admitted = problem.admit(contact, joint, f, mu, rounds, joined).astype(np.float32)
            out[name].append(engine.trial(np.ascontiguousarray(admitted[:, 0]), np.ascontiguousarray(admitted[:, 1])))
        from deepcontact.faces import solved_on_labels
        for name, source in (("labels:oracle-route", oracle), ("labels:builtin-route", np.stack(builtin, 1))):
            routed = solved_on_labels(bodies, points, source.astype(np.float64), mu, world.physics, 1e-6, 0.99,
                                      rounds)[0].astype(np.float32)
            out[name].append(engine.trial(np.ascontiguousarray(routed[:, 0]), np.ascontiguousarray(routed[:, 1])))
        engine.set_warm_start(*builtin)
        engine.solve()
        previous = points
    return {k: np.array(v, float) for k, v in out.items()}


def run(args: argparse.Namespace) -> int:
    from lab.joints_price import world_and_seeds

    parsed = world_and_seeds(args, "joint-route")
    if parsed is None:
        return 2
    spec, seeds = parsed
    from tqdm import tqdm

    runs = [price(spec, s, args.models, args.rounds) for s in tqdm(seeds, unit="sim", file=sys.stderr)]
    print(f"`{args.world}`, seeds {args.seeds}, on Box2D's own states: each answer's sweeps over Box2D's "
          f"({args.rounds} admission rounds)")
    print("| answer | mean sweeps | / builtin |\n|---|---|---|")
    for name in ANSWERS:
        ratio = ratio_interval([r[name] for r in runs], [r["builtin"] for r in runs])
        mean = float(np.mean(np.concatenate([r[name] for r in runs])))
        print(f"| {name} | {mean:.1f} | {ratio.text()} |")
    return 0
