"""A graph model's answers at recorded steps, as another model's training targets (distillation).

`deepcontact train-graph --teacher CARD` trains on what a served contact-graph model
answers at each recorded point instead of the recorded correction: a large or slow
network (the sixteen-round width-128 one averaged with its mirror image, 18 ms a step)
taught to one the deadline allows. The answer is the network's correction, denormalized
and before the server's combine (what `GraphPredictor` adds to Box2D's warm start with
a correction_scale of 1 and no threshold), in the student's target units (N s).

    card = ModelCard.load("models/graph-mse-1-799-w128-r16-ln-gpu.json")
    y = answers(graph_set, card, card.onnx_path("models/graph-mse-1-799-w128-r16-ln-gpu.json"))
    # y: (N, T) float32 N s, row i the teacher's correction at graph_set's point i

Answers are kept as .npz beside the graph cache, keyed by the data's cache key and
the teacher's ONNX bytes, so a second run with the same teacher reads them back.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
from pathlib import Path

import numpy as np

from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCard
from training.contact_graph import GraphSet

STEPS_AT_ONCE = 32  # steps per ONNX run: one graph of a few thousand points, far from any memory limit


class TeacherError(ValueError):
    """The teacher cannot answer these steps (another kind of model, channels or targets)."""


@dataclasses.dataclass(frozen=True)
class Teacher:
    """A graph card and its network, ready to answer GraphSets."""

    card_path: Path
    card: ModelCard
    onnx_bytes: bytes

    @classmethod
    def load(cls, card_path: str | Path) -> "Teacher":
        card_path = Path(card_path)
        card = ModelCard.load(card_path)
        if card.kind != "graph":
            raise TeacherError(f"{card_path}: a teacher is a graph model (kind \"graph\"); this card's kind is "
                               f"{card.kind!r}")
        return cls(card_path, card, card.onnx_path(card_path).read_bytes())

    @property
    def digest(self) -> str:
        """The first 12 hex digits of the network's SHA-1: which answers a cache file holds."""
        return hashlib.sha1(self.onnx_bytes).hexdigest()[:12]

    def describe(self) -> dict:
        """What a student's card records of its teacher."""
        return {"card": str(self.card_path), "name": self.card.name, "onnx_sha1": self.digest}

    def check(self, gs: GraphSet) -> np.ndarray:
        """The columns of gs.features the teacher reads, in its order; raises TeacherError
        when the data lacks one of its channels or the targets differ."""
        spec = self.card.gridspec
        missing = [n for n in spec.inputs if n not in gs.inputs]
        if missing:
            raise TeacherError(f"the teacher {self.card.name} reads {', '.join(missing)}, which the student's data "
                               f"does not carry (train with --extra-inputs {','.join(missing)})")
        if tuple(spec.targets) != tuple(gs.target_names):
            raise TeacherError(f"the teacher {self.card.name} answers {', '.join(spec.targets)}; the student is "
                               f"trained on {', '.join(gs.target_names)}")
        return np.array([gs.inputs.index(n) for n in spec.inputs], np.int64)


def answers(gs: GraphSet, teacher: Teacher, *, progress=None) -> np.ndarray:
    """(N, T) float32 N s: the teacher's correction at every point of gs, in gs's point order.

    Runs STEPS_AT_ONCE steps as one graph (their disjoint union, as training batches do);
    a step's answer does not depend on the others in its batch. `progress`, if given, is
    updated with the number of steps done."""
    import onnxruntime as ort

    columns = teacher.check(gs)
    spec = teacher.card.gridspec
    in_mean, in_std = spec.normalization_arrays(spec.inputs)
    out_mean, out_std = spec.normalization_arrays(spec.targets)
    session = ort.InferenceSession(teacher.onnx_bytes, providers=["CPUExecutionProvider"])
    out = np.empty((len(gs.targets), len(spec.targets)), np.float32)
    for start in range(0, len(gs), STEPS_AT_ONCE):
        steps = np.arange(start, min(len(gs), start + STEPS_AT_ONCE))
        features, _, ends, dynamic = gs.batch(steps)
        x = ((features[:, columns] - in_mean) / in_std).astype(np.float32)
        y = session.run([teacher.card.output_name], {"points": x, "ends": ends.astype(np.int32),
                                                     "dynamic": dynamic})[0]
        out[gs.point_offsets[steps[0]]:gs.point_offsets[steps[-1] + 1]] = y * out_std + out_mean
        if progress is not None:
            progress.update(len(steps))
    return out


def taught(gs: GraphSet, teacher: Teacher, cache_file: Path, *, progress=None) -> GraphSet:
    """gs with the teacher's answers as its targets, read from `cache_file` when an earlier
    run left them there, else computed and kept there (written under a temporary name)."""
    if cache_file.exists():
        with np.load(cache_file, allow_pickle=False) as f:
            targets = f["targets"]
        if targets.shape == gs.targets.shape:
            return dataclasses.replace(gs, targets=targets)
    targets = answers(gs, teacher, progress=progress)
    buffer = io.BytesIO()
    np.savez(buffer, targets=targets)
    write_bytes_atomic(cache_file, buffer.getvalue())
    return dataclasses.replace(gs, targets=targets)
