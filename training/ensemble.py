"""Several contact-graph models served as one: the mean of their corrections.

    python -m training.ensemble models/A.json models/B.json models/C.json --name graph-ensemble3
        # models/graph-ensemble3.onnx and models/graph-ensemble3.json

Each member is a graph card (kind "graph", combine "residual") with its own
input and output normalization (statistics of the steps it was trained on).
The ensemble is one ONNX graph with the same three inputs the server feeds a
graph model (points (P, F) raw channel values, ends (P, 2), dynamic (B, 1)):

    for each member m:  x_m = (points - in_mean_m) / in_std_m
                        c_m = member_m(x_m, ends, dynamic) * out_std_m + out_mean_m   (P, 2) N s
    impulses = mean over m of c_m                                                     (P, 2) N s

so its card carries no normalization (every channel (0, 1)) and the server's
GraphPredictor serves it unchanged, thresholds (`correction_threshold`)
applied to the mean. Why: the members' errors at a point are partly their own
(different steps, losses, a graph-wide summary); the mean keeps what they
agree on. The price is one network's inference per member, run in one session.

With `--agree K` the mean is served only where the members agree, per point and
component, and Box2D's warm start (a zero correction) elsewhere:

    impulses = mean * [std over m of c_m < K * |mean|]                             (P, 2) N s

Why: at the corrections of 0.1-1 N s, where a warm start's value lies, a
single model's sign is right 60-80 % of the time and its size seldom within
half (docs/results.md, "Where the iterations are"); where members trained with
different losses agree, it is right far more often. The gate serves those
points and leaves the others to Box2D.

With `--mirror` each member also answers the step reflected left to right
(x -> -x: every input channel times its sign under the reflection,
`deepcontact.channels` Channel.mirror), and that answer reflected back counts as
one more member:

    c_m' = member_m(mirror_in * points ...) * mirror_out                          (P, 2) N s

The two steps run as one batch of two disjoint graphs (the reflected step's
bodies numbered after the sent one's), so the price is one larger inference,
not two. Why: the worlds are symmetric under the reflection and the networks
are not built to be; their answer and their mirror image's differ by about a
fifth of the answer, and the mean of the two errs less than either. A pooled
member (`pooled`: each round reads the mean state of all points it is given)
runs twice instead, in two copies, since in one batch its summary would span
both steps.

Members with probes (training/graph_model.py) also read the contact problem's
operator: geometry (P, 8), masses (P, 2), inverse (B, 2), which the ensemble then
takes too and hands on (reflected with the step under --mirror: the geometry's
columns times training.contact_graph.MIRROR_GEOMETRY).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import shlex
import sys
from pathlib import Path

import numpy as np

from deepcontact.channels import mirror_signs
from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCard, ModelCardError

GRAPH_INPUTS = ("points", "ends", "dynamic")
PHYSICS_INPUTS = ("geometry", "masses", "inverse")  # a network with probes's three more
PARITY_TOLERANCE = 1e-3  # N s; float32 sums in two orders differ by about 1e-6 here


def _member(path: Path) -> ModelCard:
    card = ModelCard.load(path)
    if card.kind != "graph" or card.combine != "residual":
        raise ModelCardError(f"{path}: an ensemble member is a graph model serving corrections "
                             f"(kind graph, combine residual); this card is kind {card.kind!r}, "
                             f"combine {card.combine!r}")
    return card


def ensemble_onnx(members: list[tuple[ModelCard, Path]], agree: float | None = None, mirror: bool = False):
    """One onnx.ModelProto averaging the members' denormalized outputs; `members`
    are (card, card path) pairs with the same input and target channels. With
    `agree` K, the mean only where the members' standard deviation is below K
    times its size (module docstring), zero elsewhere. With `mirror`, each member
    also answers the step reflected left to right, and that answer, reflected
    back, counts as one more member (module docstring)."""
    import onnx
    from onnx import TensorProto, compose, helper, numpy_helper

    first = members[0][0]
    inputs, targets = first.gridspec.inputs, first.gridspec.targets
    nodes, initializers, opsets, corrections = [], [], {}, []
    models = [onnx.load(str(card.onnx_path(path))) for card, path in members]
    physics = any(x.name in PHYSICS_INPUTS for model in models for x in model.graph.input)
    for i, ((card, path), model) in enumerate(zip(members, models)):
        got = [x.name for x in model.graph.input]
        if sorted(got) not in (sorted(GRAPH_INPUTS), sorted(GRAPH_INPUTS + PHYSICS_INPUTS)) \
                or [o.name for o in model.graph.output] != [card.output_name]:
            raise ModelCardError(f"{path}: a graph model takes {', '.join(GRAPH_INPUTS)} (and, with probes, "
                                 f"{', '.join(PHYSICS_INPUTS)}) and returns {card.output_name!r}; this one takes {got}")
        for opset in model.opset_import:
            opsets[opset.domain] = max(opsets.get(opset.domain, 0), opset.version)
        if mirror and _reads_whole_step(card):
            # A pooled member's summary is the mean over every point it is given, so the step
            # and its reflection batched together would share one: each runs in its own copy.
            parts = [(f"m{i}/", False, False), (f"m{i}r/", False, True)]
        else:
            parts = [(f"m{i}/", mirror, False)]
        for p, batched, reflected in parts:
            member_nodes, member_initializers, member_corrections = _member_graph(
                compose.add_prefix(model, p), card, p, batched, "geometry" in got, reflected)
            nodes += member_nodes
            initializers += member_initializers
            corrections += member_corrections
    if agree is None:
        nodes.append(helper.make_node("Mean", corrections, ["impulses"]))
    else:
        nodes += _agreement_gate(corrections, agree)
        initializers.append(numpy_helper.from_array(np.array(agree, np.float32), "agree"))
    graph = helper.make_graph(
        nodes, "ensemble",
        [helper.make_tensor_value_info("points", TensorProto.FLOAT, ["P", len(inputs)]),
         helper.make_tensor_value_info("ends", TensorProto.INT32, ["P", 2]),
         helper.make_tensor_value_info("dynamic", TensorProto.FLOAT, ["B", 1])]
        + ([helper.make_tensor_value_info("geometry", TensorProto.FLOAT, ["P", 8]),
            helper.make_tensor_value_info("masses", TensorProto.FLOAT, ["P", 2]),
            helper.make_tensor_value_info("inverse", TensorProto.FLOAT, ["B", 2])] if physics else []),
        [helper.make_tensor_value_info("impulses", TensorProto.FLOAT, ["P", len(targets)])],
        initializer=initializers)
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid(d, v) for d, v in sorted(opsets.items())],
                              producer_name="deepcontact.training.ensemble")
    proto.ir_version = onnx.load(str(first.onnx_path(members[0][1]))).ir_version
    onnx.checker.check_model(proto)
    return proto


def _reads_whole_step(card: ModelCard) -> bool:
    """Whether a member's rounds read all the points they are given (training.graph_model:
    `pooled`, `attention`)."""
    config = (card.architecture or {}).get("config", {})
    return bool(config.get("pooled") or config.get("attention"))


def _member_graph(model, card: ModelCard, p: str, mirror: bool, physics: bool = False,
                  reflected: bool = False) -> tuple[list, list, list[str]]:
    """One member's part of the ensemble: its nodes with their names prefixed by `p` (already
    so in `model`), from the shared raw inputs through its own normalization to its
    denormalized correction(s), N s; its initializers; the names of its corrections, one, or
    two with `mirror` (its answer to the step and to the step reflected, reflected back, run
    as one batch of two steps). `reflected` without `mirror`: its one answer is to the step
    reflected, reflected back (for a pooled member, whose two answers cannot share a batch).
    physics: the member has probes, and reads geometry, masses and inverse too."""
    from onnx import helper, numpy_helper

    from training.contact_graph import MIRROR_GEOMETRY

    inputs, targets = card.gridspec.inputs, card.gridspec.targets
    in_mean, in_std = card.gridspec.normalization_arrays(inputs)
    out_mean, out_std = card.gridspec.normalization_arrays(targets)
    initializers = [numpy_helper.from_array(value.astype(np.float32), p + name)
                    for name, value in (("in_mean", in_mean), ("in_std", in_std),
                                        ("out_mean", out_mean), ("out_std", out_std))]
    denormalize = [helper.make_node("Mul", [p + card.output_name, p + "out_std"], [p + "scaled"]),
                   helper.make_node("Add", [p + "scaled", p + "out_mean"],
                                    [p + ("both" if mirror else "correction")])]
    if not mirror and not reflected:
        nodes = [helper.make_node("Sub", ["points", p + "in_mean"], [p + "points_centred"]),
                 helper.make_node("Div", [p + "points_centred", p + "in_std"], [p + "points"]),
                 helper.make_node("Identity", ["ends"], [p + "ends"]),
                 helper.make_node("Identity", ["dynamic"], [p + "dynamic"]),
                 *(helper.make_node("Identity", [name], [p + name]) for name in (PHYSICS_INPUTS if physics else ())),
                 *model.graph.node, *denormalize]
        corrections = [p + "correction"]
    elif not mirror:
        initializers += [numpy_helper.from_array(value, p + name)
                         for name, value in (("mirror_in", mirror_signs(inputs)), ("mirror_out", mirror_signs(targets)))]
        nodes = [helper.make_node("Mul", ["points", p + "mirror_in"], [p + "reflected_raw"]),
                 helper.make_node("Sub", [p + "reflected_raw", p + "in_mean"], [p + "points_centred"]),
                 helper.make_node("Div", [p + "points_centred", p + "in_std"], [p + "points"]),
                 helper.make_node("Identity", ["ends"], [p + "ends"]),
                 helper.make_node("Identity", ["dynamic"], [p + "dynamic"])]
        if physics:
            initializers.append(numpy_helper.from_array(MIRROR_GEOMETRY, p + "mirror_geometry"))
            nodes += [helper.make_node("Mul", ["geometry", p + "mirror_geometry"], [p + "geometry"]),
                      helper.make_node("Identity", ["masses"], [p + "masses"]),
                      helper.make_node("Identity", ["inverse"], [p + "inverse"])]
        nodes += [*model.graph.node, *denormalize,
                  helper.make_node("Mul", [p + "correction", p + "mirror_out"], [p + "reflected_back"])]
        corrections = [p + "reflected_back"]
    else:
        initializers += [numpy_helper.from_array(value, p + name)
                         for name, value in (("mirror_in", mirror_signs(inputs)), ("mirror_out", mirror_signs(targets)))]
        nodes = [*_reflected_batch(p), *(_reflected_physics(p) if physics else ()), *model.graph.node, *denormalize,
                 *_halves(p)]
        if physics:
            initializers.append(numpy_helper.from_array(MIRROR_GEOMETRY, p + "mirror_geometry"))
        corrections = [p + "correction", p + "reflected_back"]
    return nodes, initializers + list(model.graph.initializer), corrections


def _reflected_batch(p: str) -> list:
    """Nodes from the graph's inputs to one member's (prefix p) batch of two disjoint steps:
    the step as sent and the step reflected left to right, each input channel times its
    mirror sign, the second step's bodies numbered after the first's. Reads the
    initializers p+in_mean, p+in_std and p+mirror_in (F,)."""
    from onnx import TensorProto, helper

    return [
        helper.make_node("Sub", ["points", p + "in_mean"], [p + "plain_centred"]),
        helper.make_node("Div", [p + "plain_centred", p + "in_std"], [p + "plain"]),
        helper.make_node("Mul", ["points", p + "mirror_in"], [p + "reflected_raw"]),
        helper.make_node("Sub", [p + "reflected_raw", p + "in_mean"], [p + "reflected_centred"]),
        helper.make_node("Div", [p + "reflected_centred", p + "in_std"], [p + "reflected"]),
        helper.make_node("Concat", [p + "plain", p + "reflected"], [p + "points"], axis=0),
        helper.make_node("Shape", ["dynamic"], [p + "body_count64"], start=0, end=1),
        helper.make_node("Cast", [p + "body_count64"], [p + "body_count"], to=TensorProto.INT32),
        helper.make_node("Add", ["ends", p + "body_count"], [p + "ends_after"]),
        helper.make_node("Concat", ["ends", p + "ends_after"], [p + "ends"], axis=0),
        helper.make_node("Concat", ["dynamic", "dynamic"], [p + "dynamic"], axis=0),
    ]


def _reflected_physics(p: str) -> list:
    """Nodes from the graph's physics inputs to one member's (prefix p) for the batch of two
    steps _reflected_batch makes: the geometry as sent and reflected (each column times its
    sign, the initializer p+mirror_geometry (8,)); masses and inverse masses do not change."""
    from onnx import helper

    return [
        helper.make_node("Mul", ["geometry", p + "mirror_geometry"], [p + "reflected_geometry"]),
        helper.make_node("Concat", ["geometry", p + "reflected_geometry"], [p + "geometry"], axis=0),
        helper.make_node("Concat", ["masses", "masses"], [p + "masses"], axis=0),
        helper.make_node("Concat", ["inverse", "inverse"], [p + "inverse"], axis=0),
    ]


def _halves(p: str) -> list:
    """Nodes from one member's (prefix p) corrections of the doubled batch, p+both (2P, T),
    to p+correction (the step as sent) and p+reflected_back (the reflected step's answer
    times each target's mirror sign). Reads the initializer p+mirror_out (T,)."""
    from onnx import helper, numpy_helper

    return [
        helper.make_node("Shape", ["points"], [p + "point_count"], start=0, end=1),
        helper.make_node("Constant", [], [p + "zero"], value=numpy_helper.from_array(np.array([0], np.int64))),
        helper.make_node("Constant", [], [p + "end"],
                         value=numpy_helper.from_array(np.array([np.iinfo(np.int64).max], np.int64))),
        helper.make_node("Slice", [p + "both", p + "zero", p + "point_count"], [p + "correction"]),
        helper.make_node("Slice", [p + "both", p + "point_count", p + "end"], [p + "reflected_answer"]),
        helper.make_node("Mul", [p + "reflected_answer", p + "mirror_out"], [p + "reflected_back"]),
    ]


def _agreement_gate(corrections: list[str], agree: float) -> list:
    """Nodes from the members' corrections (each (P, 2)) to `impulses`: their mean where
    their standard deviation (population, over members) is below agree * |mean|, else 0.
    Reads the initializer `agree`."""
    from onnx import TensorProto, helper

    squares = [f"{c}_squared" for c in corrections]
    return [
        helper.make_node("Mean", corrections, ["mean"]),
        *(helper.make_node("Mul", [c, c], [s]) for c, s in zip(corrections, squares)),
        helper.make_node("Mean", squares, ["mean_square"]),
        helper.make_node("Mul", ["mean", "mean"], ["square_mean"]),
        # E[c^2] - E[c]^2 can round below 0; the comparison is on variances, so no Sqrt.
        helper.make_node("Sub", ["mean_square", "square_mean"], ["variance"]),
        helper.make_node("Mul", ["agree", "agree"], ["agree_squared"]),
        helper.make_node("Mul", ["square_mean", "agree_squared"], ["allowed"]),
        helper.make_node("Less", ["variance", "allowed"], ["agreed"]),
        helper.make_node("Cast", ["agreed"], ["agreed_float"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["mean", "agreed_float"], ["impulses"]),
    ]


def agreed_mean(corrections: np.ndarray, agree: float | None) -> np.ndarray:
    """The served correction from the members' (M, P, 2): their mean, gated as the ONNX graph
    gates it when `agree` is given."""
    mean = corrections.mean(axis=0)
    if agree is None:
        return mean
    variance = np.mean(np.square(corrections), axis=0) - np.square(mean)
    return np.where(variance < np.square(mean) * agree**2, mean, 0.0)


def _parity(proto_bytes: bytes, members: list[tuple[ModelCard, Path]], n_points: int = 64,
            seed: int = 0, agree: float | None = None, mirror: bool = False) -> float:
    """Largest |ensemble - (gated) mean of the members run one by one| over random steps, N s
    (with `mirror`, each member also run on the reflected step, its answer reflected back)."""
    import onnxruntime as ort

    from training.contact_graph import MIRROR_GEOMETRY

    rng = np.random.default_rng(seed)
    card = members[0][0]
    n_bodies = 20
    points = rng.normal(0.0, 1.0, (n_points, len(card.gridspec.inputs))).astype(np.float32)
    ends = rng.integers(0, n_bodies, (n_points, 2)).astype(np.int32)
    dynamic = (rng.random((n_bodies, 1)) > 0.1).astype(np.float32)
    normal = rng.normal(size=(n_points, 2))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    geometry = np.concatenate([normal, normal[:, ::-1] * [1, -1], rng.uniform(-0.5, 0.5, (n_points, 4))],
                              axis=1).astype(np.float32)
    physics = {"geometry": geometry, "masses": rng.uniform(0.1, 1.0, (n_points, 2)).astype(np.float32),
               "inverse": (rng.uniform(0.5, 2.0, (n_bodies, 2)) * dynamic).astype(np.float32)}
    want = []
    for member, path in members:
        session = ort.InferenceSession(str(member.onnx_path(path)), providers=["CPUExecutionProvider"])
        reads = {i.name for i in session.get_inputs()}
        in_mean, in_std = member.gridspec.normalization_arrays(member.gridspec.inputs)
        out_mean, out_std = member.gridspec.normalization_arrays(member.gridspec.targets)
        signs = [(np.ones(len(member.gridspec.inputs), np.float32), np.ones(len(member.gridspec.targets), np.float32))]
        if mirror:
            signs.append((mirror_signs(member.gridspec.inputs), mirror_signs(member.gridspec.targets)))
        for k, (sign_in, sign_out) in enumerate(signs):
            feed = {"points": (points * sign_in - in_mean) / in_std, "ends": ends, "dynamic": dynamic}
            if "geometry" in reads:
                feed.update(physics, geometry=geometry * (MIRROR_GEOMETRY if k else 1.0))
            y = session.run([member.output_name], feed)[0]
            want.append((y * out_std + out_mean) * sign_out)
    session = ort.InferenceSession(proto_bytes, providers=["CPUExecutionProvider"])
    reads = {i.name for i in session.get_inputs()}
    got = session.run(["impulses"], {"points": points, "ends": ends, "dynamic": dynamic,
                                     **(physics if "geometry" in reads else {})})[0]
    return float(np.max(np.abs(got - agreed_mean(np.stack(want), agree))))


def build_ensemble(card_paths: list[Path], name: str, out_dir: Path | None = None,
                   agree: float | None = None, mirror: bool = False) -> Path:
    """Write out_dir/NAME.onnx and its card (default out_dir: the first member's folder);
    returns the card's path. Members must read the same channels in the same order.
    `agree` K: serve the mean only where the members agree; `mirror`: each member
    also answers the reflected step (module docstring)."""
    if len(card_paths) < (1 if mirror else 2):
        raise ValueError("an ensemble needs at least two member cards, or one with --mirror")
    if agree is not None and not agree > 0:
        raise ValueError(f"--agree must be > 0 (the members' spread allowed, as a share of their mean); got {agree}")
    members = [(_member(Path(p)), Path(p)) for p in card_paths]
    first = members[0][0]
    for card, path in members[1:]:
        if card.gridspec.inputs != first.gridspec.inputs or card.gridspec.targets != first.gridspec.targets:
            raise ModelCardError(f"{path}: reads {list(card.gridspec.inputs)} -> {list(card.gridspec.targets)}, "
                                 f"{members[0][1]} reads {list(first.gridspec.inputs)} -> "
                                 f"{list(first.gridspec.targets)}; members must agree")
    if len({card.name for card, _ in members}) < len(members):
        raise ValueError("a member is named twice")
    command = " ".join(["python -m training.ensemble", *(shlex.quote(str(p)) for p in card_paths),
                        "--name", shlex.quote(name)] + (["--out-dir", shlex.quote(str(out_dir))] if out_dir else [])
                       + (["--agree", f"{agree:g}"] if agree is not None else []) + (["--mirror"] if mirror else []))
    out_dir = Path(out_dir) if out_dir is not None else members[0][1].parent
    data = ensemble_onnx(members, agree, mirror).SerializeToString()
    parity = _parity(data, members, agree=agree, mirror=mirror)
    if not parity <= PARITY_TOLERANCE:
        raise ValueError(f"the ensemble's graph answers up to {parity:.3g} N s from its members' mean run one by one "
                         f"(allowed {PARITY_TOLERANCE:g}): nothing written")
    onnx_path = write_bytes_atomic(out_dir / f"{name}.onnx", data)
    described = [{"name": card.name, "parameters": card.parameters,
                  "onnx_sha256": hashlib.sha256(card.onnx_path(path).read_bytes()).hexdigest(),
                  "validation_loss": card.validation.get("loss"), "commands": list(card.commands)}
                 for card, path in members]
    card = ModelCard(
        name=name, kind="graph", onnx_file=onnx_path.name,
        gridspec=dataclasses.replace(first.gridspec, normalization={}),  # folded into the graph
        fixed_grid=False, input_name="points", output_name="impulses", combine="residual",
        parameters=sum(c.parameters for c, _ in members),
        architecture={"config": {"kind": "graph-ensemble", "members": [c.name for c, _ in members],
                                  **({"agree": agree} if agree is not None else {}),
                                  **({"mirror": True} if mirror else {})},
                      "onnx_bytes": len(data), "parameters": {"total": sum(c.parameters for c, _ in members)}},
        training={"ensemble_of": described}, parity_max_abs_error=parity, trained_on=_trained_on(members),
        commands=tuple(cmd for member, _ in members for cmd in member.commands) + (command,))
    return card.save(out_dir / f"{name}.json")


def _trained_on(members) -> dict | None:
    """What the members were trained on, where every one records it and all agree; else None
    (an ensemble answers for the worlds each of its members knows)."""
    seen = [card.trained_on for card, _ in members]
    return seen[0] if seen[0] is not None and all(s == seen[0] for s in seen) else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m training.ensemble",
        description="serve several contact-graph models as one: an ONNX file that averages their "
                    "corrections, with its card (members: graph cards with combine residual)")
    parser.add_argument("cards", type=Path, nargs="+", help="the members' cards, e.g. models/graph-*.json")
    parser.add_argument("--name", required=True, help="the ensemble's name: writes NAME.onnx and NAME.json")
    parser.add_argument("--out-dir", type=Path, help="where to write (default: the first member's folder)")
    parser.add_argument("--agree", type=float, metavar="K",
                        help="serve the mean correction only where the members agree: their standard deviation "
                             "below K times the mean's size (per point and component); Box2D's warm start elsewhere")
    parser.add_argument("--mirror", action="store_true",
                        help="each member also answers the step reflected left to right (x -> -x), and that "
                             "answer reflected back is averaged in as one more member: a model and its mirror "
                             "image, run as one batch of two steps")
    args = parser.parse_args(argv)
    try:
        path = build_ensemble(args.cards, args.name, args.out_dir, args.agree, args.mirror)
    except (ModelCardError, ValueError) as exc:
        print(f"ensemble: {exc}", file=sys.stderr)
        return 2
    card = ModelCard.load(path)
    what = "the members' mean" if args.agree is None else f"the members' mean where they agree (K {args.agree:g})"
    what += " (each with its mirror image)" if args.mirror else ""
    print(f"wrote {path} and {card.onnx_file}: {len(args.cards)} members, {card.parameters:,} parameters, "
          f"largest difference from {what} {card.parity_max_abs_error:.2g} N s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
