"""The contact-graph model: message passing over a step's bodies and contact points.

Where the grid models smear every point onto a grid and read it back, this
model works on the points themselves (issue 14, item 5). A step is a graph:
bodies are nodes, contact points are edges between body_a and body_b.

    net = ContactGraphNet(GraphConfig(in_channels=14, out_channels=2))
    y = net(points, ends, dynamic)
    # points (P, F) float32 normalized per-point channels
    # ends (P, 2) int32 rows of dynamic: the point's body A and body B
    # dynamic (B, 1) float32: 1 for bodies that take impulses, 0 for static ones
    # y (P, T) float32 normalized targets

Each of `rounds` rounds does what one sweep of the contact solver does in
spirit: every point sends a message to its two bodies (one for A, another for
B, since an impulse pushes them apart), each body sums what reaches it (static
bodies keep nothing: they absorb any impulse), and every point updates its
state from its own and its two bodies' sums, with a residual connection.
Sums, not means: a body's total load is what the points around it share.

With `pooled`, every round also hands each point the mean state of all points
of its step: a graph-wide summary that reaches past the rounds' few contacts
(a pile's slow, pile-wide modes are what the solver's iterations are spent on).
A batch of several steps passes `step_of` (P,), each point's step; without it
the whole input is one step, as the server runs it.

With `layer_norm`, each round reads its state through a layer normalization
(pre-norm, as deep transformers do) and so does the decoder: without it, sixteen
residual rounds did not train (docs/results.md, "Eight rounds").

With `tied`, every round uses the same weights (those named round0_*), so the
network is one learned sweep repeated: how many rounds it runs is then a choice
made at each call (`rounds=`), not a property of the weights: reach, which is
what paid from three rounds to eight, without more weights (lab/tied_rounds.py
exports other depths). Measured, it helps only at the depths it was trained at;
past them the answers get worse (docs/results.md, "One sweep, repeated"). With
`recall`, every round's update also reads the encoded inputs, so however many
rounds run, the last still sees the step it is answering.

With `body_state`, every body keeps a state of its own from round to round (B, W), as the
nodes of an encode-process-decode network do: each round adds to it what the round's sums
make of it (static bodies keep none), and points read their bodies' states instead of the
round's bare sums. Why: what the solver settles at a body is its motion, accumulated over its
sweeps from every contact; a plain round forgets each body's sum once its points have read it,
so the motion has to be carried in the points' states, split over a body's contacts. With
`body_plus_sums` as well, the points read the round's sums plus their bodies' states: a network
whose state layers end at zero is then exactly the plain network, so a trained one can grow one.

With `global_state` as well as `pooled`, every step keeps a state of its own from round to
round (S, W), grown each round by two dense layers from that state and the round's mean, and
its points read that state where a pooled network reads the bare mean. Why it was tried: a
pooled summary lowers the solver's sweeps more than its fit suggests, and a pile's slow,
pile-wide modes might want a pile-wide memory rather than a mean recomputed each round.
Screened, it fits a little better than the bare mean and prices no better (docs/results.md,
"A summary of the step at eight rounds").

With `attention` = H > 0, every round also reads a weighted mean of its step's points
(linear attention, H heads of W/H features): a point asks with a query, every point of the
step answers with a key and a value, and the point reads the values weighted by the match of
its query and their keys (positive feature maps elu + 1, so the mean over the step is
normalized as softmax's, and the cost grows with the points, not their square). The bare
mean of `pooled` is the case where every weight is equal. Why it was tried: the step's mean
lowers the solver's sweeps more than its fit suggests; a read that chooses whose state it
averages can carry a pile's load from where it is to where it is needed in one round.

With `probes` = C > 0, every round also asks the physics a question: the round's state
makes C trial impulses at each point (a normal and a tangent part each), and the round
reads back, at each point and for each trial, the relative (normal, tangent) velocity that
all points' trials together give it, times the point's effective masses (N s, what one
Jacobi sweep would change): J M^-1 J^T applied exactly, C times a round. A ReLU network
can only approximate the products of directions and impulses that this operator is made
of; here it is given them. It needs each point's geometry (normal, tangent, and its place
on both bodies) and masses, and each body's inverse mass and inertia (`physics=`), as the
training batches carry them (training.train_graph.Scaling.batch) and the server computes
them from a request (deepcontact.kinematics.contact_physics); exported, they are three more
inputs, "geometry", "masses" and "inverse".

Plain tf.Module, no Keras: the weights are a dict of arrays (saved as .npz)
and the same tf.function is trained and exported (tf2onnx, opset 17). How points
reach their bodies (`incidence`) changes the graph's ops, not its numbers: training
sums by segments, the export by one-hot matmuls or by scatter-adds.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from training.models import import_tensorflow


LAYER_NORM_EPS = 1e-5
ATTENTION_TINY = 1e-30  # the smallest match attention divides by (float32's smallest normal is 1.2e-38)
INCIDENCE_MODES = ("segments", "matmul", "scatter")


@dataclasses.dataclass(frozen=True)
class GraphConfig:
    in_channels: int
    out_channels: int = 2
    width: int = 32  # features per point and per body message
    rounds: int = 3  # message-passing rounds
    kind: str = "graph"
    pooled: bool = False  # each round also reads the mean state of the step's points
    layer_norm: bool = False  # each round reads its state through a layer normalization (pre-norm)
    tied: bool = False  # every round uses round 0's weights; `rounds` is then how many the export runs
    recall: bool = False  # each round's update also reads the encoded inputs
    probes: int = 0  # trial impulses a round sends through the contact problem's operator (0: none)
    body_state: bool = False  # each body keeps a state across rounds, updated from the round's sums
    body_plus_sums: bool = False  # with body_state, points read the round's sums plus the state, not the state alone
    global_state: bool = False  # with pooled, each step keeps a state across rounds, which its points read
    attention: int = 0  # heads of linear attention over the step's points each round reads (0: none)

    @property
    def reads_whole_step(self) -> bool:
        """Whether a point's answer depends on every point of its step, not only on those its rounds reach:
        such a network must be run one step at a time (or with step_of)."""
        return self.pooled or self.attention > 0


def _dense_shapes(c: GraphConfig) -> dict[str, tuple[int, int]]:
    """Every dense layer's (fan_in, fan_out), in the order the network uses them."""
    w = c.width
    shapes = {"encode0": (c.in_channels, w), "encode1": (w, w)}
    for r in range(1 if c.tied else c.rounds):
        shapes[f"round{r}_to_a"] = (w, w)
        shapes[f"round{r}_to_b"] = (w, w)
        if c.probes:
            shapes[f"round{r}_probe"] = (w, 2 * c.probes)
        if c.body_state:
            shapes[f"round{r}_body0"] = (2 * w, w)
            shapes[f"round{r}_body1"] = (w, w)
        if c.global_state:
            shapes[f"round{r}_global0"] = (2 * w, w)
            shapes[f"round{r}_global1"] = (w, w)
        if c.attention:
            for part in ("query", "key", "value"):
                shapes[f"round{r}_{part}"] = (w, w)
        shapes[f"round{r}_update0"] = ((3 + c.pooled + (c.attention > 0) + c.recall) * w + 2 * c.probes, w)
        shapes[f"round{r}_update1"] = (w, w)
    shapes["decode0"] = (w, w)
    shapes["decode1"] = (w, c.out_channels)
    return shapes


def _norm_names(c: GraphConfig) -> list[str]:
    """The layer normalizations, in the order the network uses them: one before each round, one before the decoder."""
    return [f"round{r}_norm" for r in range(1 if c.tied else c.rounds)] + ["decode_norm"] if c.layer_norm else []


def init_weights(c: GraphConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """Glorot-uniform kernels, zero biases; the last layer starts at zero, so an
    untrained model predicts the targets' mean (no correction for residual targets).
    Layer normalizations start as gain 1, offset 0."""
    rng = np.random.default_rng(seed)
    weights = {}
    for name, (fan_in, fan_out) in _dense_shapes(c).items():
        limit = np.sqrt(6.0 / (fan_in + fan_out))
        kernel = rng.uniform(-limit, limit, (fan_in, fan_out))
        if name == "decode1":
            kernel = np.zeros_like(kernel)
        weights[f"{name}/kernel"] = kernel.astype(np.float32)
        weights[f"{name}/bias"] = np.zeros(fan_out, np.float32)
    for name in _norm_names(c):
        weights[f"{name}/gain"] = np.ones(c.width, np.float32)
        weights[f"{name}/offset"] = np.zeros(c.width, np.float32)
    return weights


def count_parameters(weights: dict[str, np.ndarray]) -> int:
    return int(sum(w.size for w in weights.values()))


class ContactGraphNet:
    """The network as TensorFlow variables and one forward function (see the module docstring)."""

    def __init__(self, config: GraphConfig, weights: dict[str, np.ndarray] | None = None, seed: int = 0,
                 incidence: str = "segments"):
        tf = import_tensorflow()
        self.tf = tf
        self.config = config
        # How points reach their bodies: "segments" (unsorted_segment_sum, fast in TF on big
        # batches), "matmul" (one-hot incidence matrices, (P, B): fast in ONNX Runtime on
        # small steps, where tf2onnx turns segment sums into a sort, but its cost grows with
        # points times bodies) or "scatter" (tensor_scatter_nd_add, which tf2onnx writes as
        # ONNX ScatterND with reduction "add": cost grows with the points alone).
        # The same sums every way.
        if incidence not in INCIDENCE_MODES:
            raise ValueError(f"incidence {incidence!r} is not one of {', '.join(INCIDENCE_MODES)}")
        if config.global_state and not config.pooled:
            raise ValueError("a step's state (global_state) is read where a pooled network reads its summary: "
                             "it needs pooled")
        if config.attention < 0 or (config.attention and config.width % config.attention):
            raise ValueError(f"attention heads must divide the width {config.width}; got {config.attention}")
        self.incidence = incidence
        weights = init_weights(config, seed) if weights is None else weights
        self.variables = {k: tf.Variable(v, name=k.replace("/", "_")) for k, v in sorted(weights.items())}

    @property
    def trainable(self) -> list:
        return list(self.variables.values())

    def weights(self) -> dict[str, np.ndarray]:
        return {k: v.numpy() for k, v in self.variables.items()}

    def _dense(self, x, name: str, relu: bool = True):
        y = self.tf.matmul(x, self.variables[f"{name}/kernel"]) + self.variables[f"{name}/bias"]
        return self.tf.nn.relu(y) if relu else y

    def _norm(self, x, name: str):
        """(P, W) -> (P, W): each row to zero mean and unit variance, then the layer's gain and offset.
        Without layer_norm, x itself: the network is then exactly the one without these layers."""
        if not self.config.layer_norm:
            return x
        tf = self.tf
        mean = tf.reduce_mean(x, axis=1, keepdims=True)
        var = tf.reduce_mean(tf.square(x - mean), axis=1, keepdims=True)
        return (x - mean) * tf.math.rsqrt(var + LAYER_NORM_EPS) * self.variables[f"{name}/gain"] + self.variables[f"{name}/offset"]

    def __call__(self, points, ends, dynamic, step_of=None, rounds: int | None = None, physics=None):
        """points (P, F), ends (P, 2), dynamic (B, 1) as in the module docstring;
        step_of (P,) int32, each point's step, read only by a pooled network; rounds, how
        many to run (only a tied network may run other than config.rounds); physics, for a
        network with probes: (geometry (P, 8), masses (P, 2) kg, inverse (B, 2)) as
        training.contact_graph.GraphSet.solver_batch gives them."""
        if rounds is not None and rounds != self.config.rounds and not self.config.tied:
            raise ValueError(f"an untied network runs its {self.config.rounds} rounds, not {rounds}")
        if self.config.probes and physics is None:
            raise ValueError("a network with probes needs physics=(geometry, masses, inverse)")
        tf = self.tf
        h = encoded = self._dense(self._dense(points, "encode0"), "encode1")
        a, b = ends[:, 0], ends[:, 1]
        n_bodies = tf.shape(dynamic)[0]
        # Built once, used by every round: the one-hot matrices are the costly part of "matmul".
        at_a = at_b = None
        if self.incidence == "matmul":
            at_a, at_b = tf.one_hot(a, n_bodies), tf.one_hot(b, n_bodies)  # (P, B)
        body = tf.zeros([n_bodies, self.config.width], h.dtype) if self.config.body_state else None  # (B, W)
        glob = tf.zeros_like(self._per_step(h, step_of)) if self.config.global_state else None  # (S, W)
        for r in range(self.config.rounds if rounds is None else rounds):  # loop over rounds, not points
            r = 0 if self.config.tied else r
            # Pre-norm: the residual stream h is summed, never normalized, so deep stacks keep
            # their gradients; each round reads a normalized copy.
            x = self._norm(h, f"round{r}_norm")
            to_a = self._dense(x, f"round{r}_to_a")
            to_b = self._dense(x, f"round{r}_to_b")
            load = (self._sum_at_bodies(to_a, a, at_a, n_bodies)
                    + self._sum_at_bodies(to_b, b, at_b, n_bodies)) * dynamic
            if body is not None:
                # Residual like the points' own: the body's state grows by what this round adds.
                step = self._dense(self._dense(tf.concat([body, load], axis=1), f"round{r}_body0"),
                                   f"round{r}_body1", relu=False)
                body = body + step * dynamic
                load = load + body if self.config.body_plus_sums else body
            u = tf.concat([x, self._read_bodies(load, a, at_a), self._read_bodies(load, b, at_b)], axis=1)
            if glob is not None:
                # As a body's state: the step's grows by what its points' mean this round adds.
                glob = glob + self._dense(self._dense(tf.concat([glob, self._per_step(x, step_of)], axis=1),
                                                      f"round{r}_global0"), f"round{r}_global1", relu=False)
                u = tf.concat([u, self._at_points(glob, step_of, x)], axis=1)
            elif self.config.pooled:
                u = tf.concat([u, self._step_mean(x, step_of)], axis=1)
            if self.config.attention:
                u = tf.concat([u, self._attend(x, step_of, f"round{r}")], axis=1)
            if self.config.recall:
                u = tf.concat([u, encoded], axis=1)
            if self.config.probes:
                trials = self._dense(x, f"round{r}_probe", relu=False)
                u = tf.concat([u, self._probe(trials, a, b, at_a, at_b, *physics)], axis=1)
            h = h + self._dense(self._dense(u, f"round{r}_update0"), f"round{r}_update1", relu=False)
        return self._dense(self._dense(self._norm(h, "decode_norm"), "decode0"), "decode1", relu=False)

    def _probe(self, trials, a, b, at_a, at_b, geometry, masses, inverse):
        """trials (P, 2C): C trial impulses at each point (normal parts, then tangent parts,
        N s) -> (P, 2C): the effective mass times the relative velocity all of them together
        give each point, per trial (normal parts, then tangent parts): m_eff * (J M^-1 J^T) trials.
        a, b (P,) and at_a, at_b as in __call__; geometry (P, 8), masses (P, 2) kg, inverse (B, 2).
        The C trials go through J^T, M^-1 and J side by side as columns, so the sums per body
        are the network's own (segments, matmul or scatter) and the export needs no other op."""
        tf, c = self.tf, self.config.probes
        n, t, ra, rb = geometry[:, 0:2], geometry[:, 2:4], geometry[:, 4:6], geometry[:, 6:8]
        normal, tangent = trials[:, :c], trials[:, c:]
        ix = normal * n[:, 0:1] + tangent * t[:, 0:1]  # (P, C) impulse on B along x; its opposite on A
        iy = normal * n[:, 1:2] + tangent * t[:, 1:2]
        on_b = tf.concat([ix, iy, rb[:, 0:1] * iy - rb[:, 1:2] * ix], axis=1)  # (P, 3C) force x, y, torque
        on_a = tf.concat([ix, iy, ra[:, 0:1] * iy - ra[:, 1:2] * ix], axis=1)
        n_bodies = tf.shape(inverse)[0]
        total = self._sum_at_bodies(on_b, b, at_b, n_bodies) - self._sum_at_bodies(on_a, a, at_a, n_bodies)
        scale = tf.concat([tf.tile(inverse[:, 0:1], [1, 2 * c]), tf.tile(inverse[:, 1:2], [1, c])], axis=1)
        motion = total * scale  # (B, 3C): velocity x, y and angular velocity per trial

        def at(body, one_hot, r):  # (P, C) x and y velocity of each point's place on its body
            m = self._read_bodies(motion, body, one_hot)
            w = m[:, 2 * c:]
            return m[:, :c] - w * r[:, 1:2], m[:, c:2 * c] + w * r[:, 0:1]

        (bx, by), (ax, ay) = at(b, at_b, rb), at(a, at_a, ra)
        rx, ry = bx - ax, by - ay
        return tf.concat([masses[:, 0:1] * (rx * n[:, 0:1] + ry * n[:, 1:2]),
                          masses[:, 1:2] * (rx * t[:, 0:1] + ry * t[:, 1:2])], axis=1)

    def _sum_at_bodies(self, messages, body, one_hot, n_bodies):
        """messages (P, W), body (P,) int32 each point's body, one_hot (P, B) float32 of body
        (only with "matmul", else None) -> (B, W): the sum of the messages each body receives."""
        tf = self.tf
        if self.incidence == "matmul":
            return tf.matmul(one_hot, messages, transpose_a=True)
        if self.incidence == "scatter":
            # Indices (P, 1): each point adds its whole row W into row body of the sums.
            zeros = tf.zeros([n_bodies, tf.shape(messages)[1]], messages.dtype)
            return tf.tensor_scatter_nd_add(zeros, body[:, None], messages)
        return tf.math.unsorted_segment_sum(messages, body, n_bodies)

    def _read_bodies(self, load, body, one_hot):
        """load (B, W), body (P,) int32, one_hot (P, B) or None -> (P, W): each point's body's row."""
        if self.incidence == "matmul":
            return self.tf.matmul(one_hot, load)
        return self.tf.gather(load, body)

    def _attend(self, x, step_of, name: str):
        """x (P, W) -> (P, W): for each point and head, the mean of its step's values weighted by
        the match of its query with their keys (linear attention, see the module docstring)."""
        tf, heads, w = self.tf, self.config.attention, self.config.width
        d = w // heads
        query = tf.reshape(tf.nn.elu(self._dense(x, f"{name}_query", relu=False)) + 1.0, [-1, heads, d])
        key = tf.reshape(tf.nn.elu(self._dense(x, f"{name}_key", relu=False)) + 1.0, [-1, heads, d])
        value = tf.reshape(self._dense(x, f"{name}_value", relu=False), [-1, heads, d])
        # Per step and head: the mean over points of key (x) value, (d, d), and of key, (d,);
        # means, not sums, so a step's size does not scale them (their ratio is the same).
        pairs = tf.reshape(key[:, :, :, None] * value[:, :, None, :], [-1, heads * d * d])
        per_step = self._per_step(tf.concat([pairs, tf.reshape(key, [-1, w])], axis=1), step_of)  # (S, H d d + W)
        at = tf.gather(per_step, tf.zeros_like(x[:, 0], tf.int32)) if step_of is None else tf.gather(per_step, step_of)
        kv = tf.reshape(at[:, :heads * d * d], [-1, heads, d, d])
        k = tf.reshape(at[:, heads * d * d:], [-1, heads, d])
        numerator = tf.reduce_sum(query[:, :, :, None] * kv, axis=2)  # (P, H, d)
        # >= 0: elu + 1 underflows to 0 below about -17, and a query or key mean of zeros then
        # reads nothing (0) rather than 0 / 0.
        denominator = tf.maximum(tf.reduce_sum(query * k, axis=2, keepdims=True), ATTENTION_TINY)  # (P, H, 1)
        return tf.reshape(numerator / denominator, [-1, w])

    def _step_mean(self, h, step_of):
        """(P, W): the mean of h over each point's step."""
        return self._at_points(self._per_step(h, step_of), step_of, h)

    def _per_step(self, h, step_of):
        """h (P, W) -> (S, W): its mean over each step's points; one row where step_of is None
        (the whole input is one step, as the server runs it)."""
        tf = self.tf
        if step_of is None:
            return tf.reduce_mean(h, axis=0, keepdims=True)
        n_steps = tf.reduce_max(step_of) + 1
        total = tf.math.unsorted_segment_sum(h, step_of, n_steps)
        count = tf.math.unsorted_segment_sum(tf.ones_like(h[:, :1]), step_of, n_steps)
        return total / tf.maximum(count, 1.0)

    def _at_points(self, per_step, step_of, h):
        """per_step (S, W) -> (P, W), h's rows: each point's step's row."""
        if step_of is None:
            return self.tf.zeros_like(h) + per_step
        return self.tf.gather(per_step, step_of)

    def signature(self) -> list:
        tf = self.tf
        return [tf.TensorSpec((None, self.config.in_channels), tf.float32, name="points"),
                tf.TensorSpec((None, 2), tf.int32, name="ends"),
                tf.TensorSpec((None, 1), tf.float32, name="dynamic")] + ([
                tf.TensorSpec((None, 8), tf.float32, name="geometry"),
                tf.TensorSpec((None, 2), tf.float32, name="masses"),
                tf.TensorSpec((None, 2), tf.float32, name="inverse")] if self.config.probes else [])


def config_to_dict(c: GraphConfig) -> dict[str, Any]:
    """The config as a card records it; `tied`, `recall`, `probes`, the body state's two flags, `global_state` and `attention` only where set, so
    other cards read as before them."""
    d = dataclasses.asdict(c)
    for key in ("tied", "recall", "probes", "body_state", "body_plus_sums", "global_state", "attention"):
        if not d[key]:
            del d[key]
    return d


def to_onnx(net: ContactGraphNet, opset: int = 17, incidence: str = "scatter") -> bytes:
    """The network as ONNX: inputs "points", "ends", "dynamic" (and, with probes, "geometry",
    "masses", "inverse"), output "impulses".
    `incidence` picks how the exported graph sums per body (ContactGraphNet): "scatter"
    (the default since round 2's eight-round default), ScatterND adds (opset 16 or later),
    whose cost does not grow with the bodies and which ran the default 2x faster than
    "matmul" even on the thesis world's steps (docs/performance.md); "matmul", one-hot (P, B)
    matrices, what every model before it was exported with. training.train_graph checks
    the export against `net`."""
    if incidence == "scatter" and opset < 16:
        raise ValueError(f"a scatter export needs opset 16 or later (ScatterND's reduction), not {opset}")
    import logging

    logging.getLogger("tf2onnx").setLevel(logging.ERROR)
    import tf2onnx

    tf = net.tf
    net = ContactGraphNet(net.config, net.weights(), incidence=incidence)

    if net.config.probes:
        @tf.function(input_signature=net.signature())
        def forward(points, ends, dynamic, geometry, masses, inverse):
            return {"impulses": net(points, ends, dynamic, physics=(geometry, masses, inverse))}
    else:
        @tf.function(input_signature=net.signature())
        def forward(points, ends, dynamic):
            return {"impulses": net(points, ends, dynamic)}

    proto, _ = tf2onnx.convert.from_function(forward, input_signature=net.signature(), opset=opset)
    return proto.SerializeToString()
