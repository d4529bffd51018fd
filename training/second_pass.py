"""Recorded steps as a graph model's second pass sees them: the warm start moved by its first.

A card with `passes: 2` (deepcontact.modelcard) runs its network twice: the second pass
reads the channels at the first pass's warm start in place of Box2D's and adds a
correction to it. A network trained only on Box2D's warm starts overshoots there
(docs/results.md, "A second pass"); `train-graph --second-pass CARD` trains it on both:

    a  = answers(gs, teacher)              # (N, 2) N s, the first pass's correction
    gs2 = moved(gs, a)                      # the same steps, warm start builtin + a

`train-graph --passes K` trains the network as such a card serves it, the inputs moved
inside the training graph by the same rule (`moves`), the gradient flowing through every pass.

In gs2 every channel that reads the warm start is what the server computes from it, and
the targets are what is left to correct (recorded impulse - (builtin + a)); the rest is
unchanged (the geometry, the velocities before the solve, which points are new to Box2D).
The velocities after the warm start move by A a (training.graph_loss.apply_delassus,
the impulses' effect on every body's motion, read at the points), so no engine is needed.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from training.contact_graph import GraphSet

#: the channels that read the warm start and how they move with it; new_point reads only
#: whether Box2D had the point, and a second pass keeps that (the server does as well).
MOVED = ("builtin_normal", "builtin_tangent", "vn_builtin", "vt_builtin", "jacobi_normal", "jacobi_tangent")
KEPT = ("new_point",)
TARGETS = ("correction_normal", "correction_tangent")


class SecondPassError(ValueError):
    """These steps cannot be moved (a channel or target that does not follow the warm start here)."""


def check_inputs(inputs: tuple[str, ...]) -> None:
    """Raise SecondPassError unless every warm-start channel among `inputs` is one a
    second pass recomputes (MOVED) or keeps (KEPT), and the warm start is among them."""
    from deepcontact.channels import CHANNELS

    reads_warm = [n for n in inputs if "builtin" in CHANNELS[n].needs and n not in MOVED + KEPT]
    if reads_warm:
        raise SecondPassError(f"a second pass moves {', '.join(MOVED)} with the warm start; "
                              f"{', '.join(reads_warm)} would need the engine")
    for n in ("builtin_normal", "builtin_tangent"):
        if n not in inputs:
            raise SecondPassError(f"a second pass needs the warm start among the inputs ({n})")


def check(gs: GraphSet) -> None:
    """check_inputs for gs's inputs, and its targets the correction to Box2D's warm start."""
    check_inputs(gs.inputs)
    if tuple(gs.target_names) != TARGETS:
        raise SecondPassError(f"a second pass trains on {', '.join(TARGETS)}, not {', '.join(gs.target_names)}")


def moves(inputs: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(W, V, J), each (2, F) float32: how the F `inputs` move when the warm start moves by
    a correction c (P, 2) N s that changes the points' velocities by v = A c (P, 2) m/s:

        inputs' = inputs + c @ W + v @ V - (m_eff * v) @ J

    (the warm start itself, the velocities after it, and the Jacobi step -m_eff v)."""
    check_inputs(inputs)
    out = np.zeros((3, 2, len(inputs)), np.float32)
    for k, names in enumerate((("builtin_normal", "builtin_tangent"), ("vn_builtin", "vt_builtin"),
                               ("jacobi_normal", "jacobi_tangent"))):
        for component, name in enumerate(names):
            if name in inputs:
                out[k, component, inputs.index(name)] = 1.0
    return out[0], out[1], out[2]


def delassus(gs: GraphSet, impulses: np.ndarray) -> np.ndarray:
    """A impulses: the relative (normal, tangent) velocity, (N, 2) float64 m/s, that
    impulses (N, 2) N s at gs's points give each point through its two bodies."""
    import tensorflow as tf

    from training.graph_loss import apply_delassus

    counts = np.diff(gs.point_offsets)
    ends = gs.ends.astype(np.int64) + np.repeat(gs.body_offsets[:-1], counts)[:, None]  # rows of all bodies
    out = apply_delassus(tf.constant(impulses, tf.float64), tf.constant(ends), tf.constant(gs.geometry, tf.float64),
                         tf.constant(gs.inverse, tf.float64))
    return out.numpy()


def moved(gs: GraphSet, correction: np.ndarray) -> GraphSet:
    """gs with its warm start moved from builtin to builtin + correction (N, 2) N s: the
    warm-start channels recomputed, the targets what is left to correct."""
    check(gs)
    correction = np.asarray(correction, np.float64)
    if correction.shape != (len(gs.targets), 2):
        raise SecondPassError(f"a correction per point, ({len(gs.targets)}, 2), got {correction.shape}")
    warm, velocity, jacobi = moves(gs.inputs)
    dv = delassus(gs, correction)
    features = gs.features.astype(np.float64) + correction @ warm + dv @ velocity - (gs.masses * dv) @ jacobi
    return dataclasses.replace(
        gs, features=features.astype(np.float32),
        targets=(gs.targets.astype(np.float64) - correction).astype(np.float32),
        builtin=(gs.builtin.astype(np.float64) + correction).astype(np.float32))
