"""`deepcontact lab inference`: what ONNX Runtime levers do to a grid model's inference.

    deepcontact lab inference --model pressure

Records a thesis world on a benchmark seed, turns its steps into the model's
normalized input grids exactly as the server does, and times one inference per
step for each variant, in turn (variant by variant within each step, so that
the machine's noise falls on all alike), one thread each:

    default         the server's session (ONNX Runtime's defaults, one thread)
    no-spinning     intra-op threads do not spin while idle
    extended/basic  lower graph-optimization levels than the default "all"
    no-arena        without the CPU memory arena
    int8            static int8 quantization (QDQ, per channel), calibrated on
                    other steps of the same kind (onnxruntime.quantization); its
                    output's RMS error against the float model is printed beside it
    rows=N          the grid cut to its lowest N rows (where the pile lies): the
                    time a model would take if the server ran it on the occupied
                    part of the box only

Medians and the ratio to `default`, one run. Needs a grid model (kind other
than "graph").
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_models_argument, add_seed_argument
from deepcontact.io import write_json_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_models_argument(parser)
    # Not "default": the shipped default is a contact-graph model, which has no grid to crop.
    parser.add_argument("--model", default="pressure",
                        help="grid model to time (default: %(default)s, the thesis's model)")
    add_seed_argument(parser, "thesis-world seed (default 900)", default=900)
    parser.add_argument("--steps", type=int, default=250, help="steps recorded (default 250)")
    parser.add_argument("--repeats", type=int, default=3, help="times each step is timed per variant (default 3)")
    parser.add_argument("--rows", default="32,24", help="grid heights for the cropped variants (default %(default)s)")
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")


def input_grids(card, recorded) -> list[np.ndarray]:
    """The (1, ny, nx, Cin) float32 grids the server would feed the model, one per step with contacts."""
    from deepcontact.features import world_to_grids
    from server.predictors import _Normalization
    from simclient.scene import SceneSpec

    physics = SceneSpec.thesis().physics
    norm = _Normalization(card.gridspec)
    grids, previous = [], None
    for bodies, points, _ in recorded:
        if len(points):
            g = world_to_grids(bodies, points, card.gridspec, previous=previous, physics=physics, outside="drop")
            grids.append(norm.inputs(np.ascontiguousarray(g, np.float32)).copy())
        previous = points
    return grids


def _session(path, level=None, arena=True, **config):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    options.log_severity_level = 3
    if level is not None:
        options.graph_optimization_level = level
    options.enable_cpu_mem_arena = arena
    for key, value in config.items():
        options.add_session_config_entry(key, value)
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def quantized(onnx_path: Path, input_name: str, calibration: list[np.ndarray], out: Path) -> Path:
    """Static int8 quantization of the model (QDQ, per-channel weights), calibrated on `calibration`."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.grids = iter(calibration)

        def get_next(self):
            x = next(self.grids, None)
            return None if x is None else {input_name: x}

    pre = out.with_name("pre.onnx")
    quant_pre_process(str(onnx_path), str(pre), skip_symbolic_shape=True)
    quantize_static(str(pre), str(out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
    return out


def time_in_turns(session_of: dict, feed, grids, repeats: int) -> dict[str, list[float]]:
    """Seconds per run of each named session on every grid, `repeats` times each.

    The variants take turns on each grid, so a slow spell of a shared machine
    falls on all of them alike; each session's first run plans its memory and is
    not timed. feed(name, grid) gives that session's inputs.
    """
    for name, session in session_of.items():
        session.run(None, feed(name, grids[0]))
    times = {n: [] for n in session_of}
    for x in grids:  # loop over steps
        for _ in range(repeats):
            for name, session in session_of.items():
                inputs = feed(name, x)
                t0 = time.perf_counter()
                session.run(None, inputs)
                times[name].append(time.perf_counter() - t0)
    return times


class _Refused(ValueError):
    """The arguments name nothing this bench can time; the message says why."""


def _checked(args: argparse.Namespace):
    """(card, card_path, crop heights) from the arguments, or _Refused."""
    from deepcontact.modelcard import ModelCard, ModelCardError

    card_path = args.models / f"{args.model}.json"
    try:
        card = ModelCard.load(card_path)
    except (ModelCardError, OSError) as exc:
        raise _Refused(str(exc)) from exc
    if card.kind == "graph":
        raise _Refused(f"{args.model} is a graph model; this bench times grid models (bench server times any model)")
    try:
        rows = [int(r) for r in args.rows.split(",") if r]
    except ValueError:
        raise _Refused(f"--rows takes heights like 32,24, got {args.rows!r}") from None
    return card, card_path, rows


def _variant_sessions(onnx_path: Path, input_name: str, calibration: list[np.ndarray]) -> dict:
    """{variant: InferenceSession} for the variants the module docstring lists (rows=N aside)."""
    import onnxruntime as ort

    level = ort.GraphOptimizationLevel
    with tempfile.TemporaryDirectory() as tmp:
        int8_path = quantized(onnx_path, input_name, calibration, Path(tmp) / "int8.onnx")
        return {
            "default": _session(onnx_path),
            "no-spinning": _session(onnx_path, **{"session.intra_op.allow_spinning": "0"}),
            "extended": _session(onnx_path, level.ORT_ENABLE_EXTENDED),
            "basic": _session(onnx_path, level.ORT_ENABLE_BASIC),
            "no-arena": _session(onnx_path, arena=False),
            "int8": _session(int8_path),
        }


def run(args: argparse.Namespace) -> int:
    from bench.server import record_steps

    try:
        card, card_path, rows = _checked(args)
    except _Refused as exc:
        print(f"deepcontact lab inference: {exc}", file=sys.stderr)
        return 2
    grids = input_grids(card, record_steps(args.seed, args.steps))
    if len(grids) < 8:
        print(f"deepcontact lab inference: only {len(grids)} steps with contacts; give more --steps", file=sys.stderr)
        return 2
    calibration, timed = grids[::2][:64], grids[1::2]  # calibrate and time on different steps
    sessions = _variant_sessions(card.onnx_path(card_path), card.input_name, calibration)
    crops = {f"rows={r}": r for r in rows if r < card.gridspec.ny}

    def feed(name, x):
        return {card.input_name: x if name not in crops else np.ascontiguousarray(x[:, :crops[name]])}

    names = list(sessions) + list(crops)
    session_of = {**sessions, **{c: sessions["default"] for c in crops}}
    times = time_in_turns(session_of, feed, timed, args.repeats)
    out = card.output_name
    reference = [sessions["default"].run([out], {card.input_name: x})[0] for x in timed]
    errors = [sessions["int8"].run([out], {card.input_name: x})[0] - r for x, r in zip(timed, reference)]
    int8_rms = float(np.sqrt(np.mean([np.mean(e ** 2) for e in errors])))
    output_rms = float(np.sqrt(np.mean([np.mean(r ** 2) for r in reference])))
    median = {n: 1e3 * statistics.median(v) for n, v in times.items()}
    print(f"{args.model} ({card.gridspec.ny}x{card.gridspec.nx} grid) on thesis seed {args.seed}: "
          f"{len(timed)} steps x {args.repeats}, one thread")
    print("| variant | median ms | / default |\n|---|---|---|")
    for n in names:
        print(f"| {n} | {median[n]:.3f} | {median[n] / median['default']:.2f} |")
    print(f"int8 output error: RMS {int8_rms:.3f} against the float model's output RMS {output_rms:.3f} "
          "(normalized units)")
    if args.json:
        write_json_atomic(args.json, {"model": args.model, "seed": args.seed, "steps": len(timed),
                                      "repeats": args.repeats, "median_ms": median,
                                      "int8_rms_error": int8_rms, "output_rms": output_rms})
    return 0
