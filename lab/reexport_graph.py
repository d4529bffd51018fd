"""A shipped contact-graph model exported again with the current export, its weights unchanged.

    python -m lab.reexport_graph models/graph-projected-max-1-799-r8.json
        # models/graph-projected-max-1-799-r8.onnx rewritten with ScatterND sums; its card,
        # and every card of the folder that serves the same file (the -t1 card), say so

The models exported before `training.graph_model.to_onnx` summed per body with ScatterND
adds did it with one-hot (P, B) matrices, whose cost grows with points times bodies
(docs/performance.md). The network is the same either way, so a shipped file need not be
trained again to get the faster export: its weights are recovered (training.recover_weights),
exported the current way, and the two files are run side by side on random steps of 40
to 1,600 points; the new file is written (to a temporary name, then renamed) only if they
agree within 1e-4 in normalized units. The cards keep everything they said, gain
architecture.onnx_incidence and the new onnx_bytes, and this command is added to their
commands.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCard, ModelCardError
from training.recover_weights import PARITY_TOLERANCE, RecoveryError, exported_incidence, recover


def _steps(in_channels: int, seed: int = 2) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Random steps (points (P, F), ends (P, 2) int32, dynamic (B, 1)) from 40 points among
    12 bodies to 1,600 among 1,600, a few bodies static."""
    rng = np.random.default_rng(seed)
    out = []
    for p, b in ((40, 12), (140, 100), (400, 400), (1600, 1600)):
        points = rng.standard_normal((p, in_channels)).astype(np.float32)
        ends = rng.integers(0, b, size=(p, 2)).astype(np.int32)
        dynamic = (rng.random((b, 1)) < 0.95).astype(np.float32)
        out.append((points, ends, dynamic))
    return out


def largest_difference(old: bytes, new: bytes, in_channels: int) -> float:
    """The largest |old - new| over the outputs of the two ONNX files on _steps."""
    import onnxruntime as ort

    sessions = [ort.InferenceSession(x, providers=["CPUExecutionProvider"]) for x in (old, new)]
    worst = 0.0
    for points, ends, dynamic in _steps(in_channels):
        feed = {"points": points, "ends": ends, "dynamic": dynamic}
        a, b = (s.run(["impulses"], feed)[0] for s in sessions)
        worst = max(worst, float(np.max(np.abs(a - b))))
    return worst


def reexport(card_path: Path, command: str = "") -> tuple[list[Path], float]:
    """(the cards rewritten, the largest difference between old and new file). Raises
    RecoveryError where the weights cannot be recovered or the files disagree."""
    from training.graph_model import ContactGraphNet, GraphConfig, to_onnx

    card = ModelCard.load(card_path)
    onnx_path = card.onnx_path(card_path)
    old = onnx_path.read_bytes()
    weights, parity = recover(card_path)
    if parity > PARITY_TOLERANCE:
        raise RecoveryError(f"{card_path}: the recovered network differs from its ONNX file by {parity:.2e}")
    config = GraphConfig(**card.architecture["config"])
    new = to_onnx(ContactGraphNet(config, weights))
    difference = largest_difference(old, new, config.in_channels)
    if difference > PARITY_TOLERANCE:
        raise RecoveryError(f"{card_path}: the new export differs from the old by {difference:.2e} "
                            f"(more than {PARITY_TOLERANCE}); nothing written")
    siblings = [p for p in sorted(card_path.parent.glob("*.json")) if _serves(p, onnx_path)]
    write_bytes_atomic(onnx_path, new)
    for path in siblings:
        sibling = ModelCard.load(path)
        architecture = {**sibling.architecture, "onnx_bytes": len(new), "onnx_incidence": exported_incidence(new)}
        commands = sibling.commands + ((command,) if command else ())
        dataclasses.replace(sibling, architecture=architecture, commands=commands).save(path)
    return siblings, difference


def _serves(card_path: Path, onnx_path: Path) -> bool:
    """Whether the card at card_path is a model card whose file is onnx_path. Alias cards
    (models/default.json) name a card, not a file: ModelCard.load would resolve them, and
    saving that would turn the alias into a copy."""
    try:
        if "alias_of" in json.loads(card_path.read_text()):
            return False
        card = ModelCard.load(card_path)
    except (ModelCardError, OSError, ValueError):
        return False  # not a card
    return card.onnx_path(card_path).resolve() == onnx_path.resolve()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.reexport_graph",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("cards", type=Path, nargs="+", help="contact-graph model cards, e.g. "
                                                            "models/graph-projected-max-1-799-r8.json")
    args = parser.parse_args(argv)
    command = "python -m lab.reexport_graph " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    for card_path in args.cards:
        try:
            card = ModelCard.load(card_path)
            if exported_incidence(card.onnx_path(card_path).read_bytes()) == "scatter":
                print(f"{card_path}: already exported with scatter sums; nothing to do")
                continue
            rewritten, difference = reexport(card_path, command)
        except (ModelCardError, RecoveryError, OSError) as e:
            print(f"reexport_graph: {e}", file=sys.stderr)
            return 2
        print(f"{card.onnx_path(card_path)}: exported again with scatter sums (largest difference "
              f"{difference:.1e}); cards updated: {', '.join(p.name for p in rewritten)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
