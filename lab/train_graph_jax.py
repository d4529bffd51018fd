"""The contact-graph network trained with JAX, for a machine with an accelerator.

    python -m lab.train_graph_jax --train data/a.h5 --train data/b.h5 \\
        --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5 \\
        --config 128x3 --config 128x8 --seconds 300 --out runs/jax

The question it answers (docs/results.md, "Far more training"): is the
contact-graph model's fit of the correction limited by the compute two cores
can give it, or by what its inputs say? `deepcontact train-graph` trains in
TensorFlow on the CPU; this trains the same network (training.graph_model:
the same layers, names and initialization, message passing by segment sums)
on the same channels with the same loss (`--loss mse`: each point's squared
error in normalized units, summed over normal and tangent) for a wall-clock
budget, several networks at once on one stream of batches, each on its own
cosine schedule over `--seconds`.

It writes, per network, OUT/NAME.weights.npz (the layout train-graph's
--init and training.graph_model read, kernels (fan_in, fan_out)), and
OUT/probe.json: the training files' normalization (what the card carries),
each network's validation history and the loss of no correction.
`python -m lab.import_graph_weights` turns a weights file into a served
ONNX model and its card on a machine with TensorFlow.

Steps are batched as train-graph batches them (GraphSet.batch: a disjoint
union), padded to a few fixed sizes so that XLA compiles a handful of shapes:
padded points belong to a padded static body and weigh nothing in the loss.
The training files are read by one process each (build_graph_set), so many
files read in parallel.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import queue
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from training.contact_graph import GRAPH_INPUTS, GRAPH_TARGETS, GraphSet, build_graph_set
from training.graph_model import LAYER_NORM_EPS, GraphConfig, init_weights

POINT_BUCKET = 16384  # points per batch are padded to a multiple of this (--point-bucket)
BODY_BUCKET = 2048
VAL_STEPS = 500  # per validation file, drawn as train-graph draws them (--max-val-steps)


def parse_config(text: str) -> tuple[int, int, bool]:
    """'WIDTHxROUNDS' -> (width, rounds, False); 'WIDTHxROUNDSn' -> (width, rounds, True): with layer norms."""
    t = text.lower()
    norm = t.endswith("n")
    try:
        width, rounds = (int(x) for x in t.removesuffix("n").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a network is WIDTHxROUNDS like 128x8, or 128x16n with layer norms, "
                                         f"got {text!r}") from None
    if width < 1 or rounds < 1:
        raise argparse.ArgumentTypeError(f"width and rounds must be >= 1, got {text!r}")
    return width, rounds, norm


def network_name(width: int, rounds: int, norm: bool) -> str:
    return f"jax-w{width}-r{rounds}" + ("-ln" if norm else "")


def _read(job: tuple[str, int | None, str]) -> str:
    """One file's graph set, saved as .npz under the given folder (no pickle between processes)."""
    path, max_steps, folder = job
    gs = build_graph_set(path, GRAPH_INPUTS, GRAPH_TARGETS, max_steps=max_steps, seed=0)
    fd, out = tempfile.mkstemp(suffix=".npz", dir=folder)
    os.close(fd)
    gs.save(out)
    return out


def read_sets(paths: list[str], max_steps: int | None, workers: int, folder: str) -> list[GraphSet]:
    with ProcessPoolExecutor(max_workers=max(1, min(workers, len(paths)))) as pool:
        saved = list(pool.map(_read, [(p, max_steps, folder) for p in paths]))
    sets = [GraphSet.load(s) for s in saved]
    for s in saved:
        Path(s).unlink()
    return sets


def concatenate(sets: list[GraphSet]) -> GraphSet:
    """One GraphSet holding every step of `sets`, in order."""
    def offsets(name: str) -> np.ndarray:
        parts, base = [np.zeros(1, np.int64)], 0
        for g in sets:
            o = getattr(g, name)
            parts.append(o[1:] + base)
            base += int(o[-1])
        return np.concatenate(parts)

    fields = ("features", "targets", "ends", "dynamic", "builtin", "geometry", "masses", "inverse", "speed")
    return GraphSet(**{f: np.concatenate([getattr(g, f) for g in sets]) for f in fields},
                    point_offsets=offsets("point_offsets"), body_offsets=offsets("body_offsets"),
                    inputs=sets[0].inputs, target_names=sets[0].target_names)


def _padded(n: int, bucket: int) -> int:
    return max(bucket, -(-n // bucket) * bucket)


def padded_batch(gs: GraphSet, steps: np.ndarray, in_mean, in_std, out_mean, out_std,
                 bucket: int = POINT_BUCKET) -> tuple:
    """Steps of gs as one normalized, padded batch: points (P', F), ends (P', 2) int32,
    dynamic (B', 1), targets (P', T), mask (P',) with 1 at the P real points. The B'
    - B >= 1 padded bodies are static and take every padded point."""
    f, t, e, d = gs.batch(steps)
    p, b = len(f), len(d)
    pp, bb = _padded(p, bucket), _padded(b + 1, BODY_BUCKET)
    points = np.zeros((pp, f.shape[1]), np.float32)
    points[:p] = (f - in_mean) / in_std
    targets = np.zeros((pp, t.shape[1]), np.float32)
    targets[:p] = (t - out_mean) / out_std
    ends = np.full((pp, 2), bb - 1, np.int32)
    ends[:p] = e
    dynamic = np.zeros((bb, 1), np.float32)
    dynamic[:b] = d
    mask = np.zeros(pp, np.float32)
    mask[:p] = 1.0
    return points, ends, dynamic, targets, mask


def _network(jax, jnp):
    """forward(params, points, ends, dynamic, rounds) as training.graph_model.ContactGraphNet."""
    def dense(params, x, name, relu=True):
        y = x @ params[f"{name}/kernel"] + params[f"{name}/bias"]
        return jax.nn.relu(y) if relu else y

    def norm(params, x, name):
        if f"{name}/gain" not in params:
            return x
        mean = jnp.mean(x, axis=1, keepdims=True)
        var = jnp.mean(jnp.square(x - mean), axis=1, keepdims=True)
        return (x - mean) * jax.lax.rsqrt(var + LAYER_NORM_EPS) * params[f"{name}/gain"] + params[f"{name}/offset"]

    def forward(params, points, ends, dynamic, rounds):
        h = dense(params, dense(params, points, "encode0"), "encode1")
        a, b = ends[:, 0], ends[:, 1]
        n = dynamic.shape[0]
        for r in range(rounds):  # loop over rounds, not points
            x = norm(params, h, f"round{r}_norm")
            to_a = dense(params, x, f"round{r}_to_a")
            to_b = dense(params, x, f"round{r}_to_b")
            load = (jax.ops.segment_sum(to_a, a, n) + jax.ops.segment_sum(to_b, b, n)) * dynamic
            u = jnp.concatenate([x, load[a], load[b]], axis=1)
            h = h + dense(params, dense(params, u, f"round{r}_update0"), f"round{r}_update1", relu=False)
        return dense(params, dense(params, norm(params, h, "decode_norm"), "decode0"), "decode1", relu=False)

    return forward


class Probe:
    """Several networks trained by Adam on one stream of batches (see the module docstring)."""

    def __init__(self, configs: list[tuple[int, int, bool]], in_channels: int, out_channels: int, out_mean, out_std,
                 lr: float, seed: int):
        import jax
        import jax.numpy as jnp

        self.jax, self.jnp, self.lr = jax, jnp, lr
        self.names = [network_name(*c) for c in configs]
        self.rounds = [r for _, r, _ in configs]
        forward = _network(jax, jnp)
        self.params, self.moments = [], []
        for w, r, norm in configs:
            weights = init_weights(GraphConfig(in_channels=in_channels, out_channels=out_channels, width=w,
                                               rounds=r, layer_norm=norm), seed)
            # Start from Box2D's own warm start, as train-graph does: a zero correction.
            weights["decode1/bias"] = ((0 - out_mean) / out_std).astype(np.float32)
            p = {k: jnp.asarray(v) for k, v in weights.items()}
            self.params.append(p)
            self.moments.append((jax.tree_util.tree_map(jnp.zeros_like, p), jax.tree_util.tree_map(jnp.zeros_like, p)))

        def loss_sums(params, points, ends, dynamic, targets, mask, rounds):
            pred = forward(params, points, ends, dynamic, rounds)
            per_point = jnp.sum(jnp.square(pred - targets), axis=1) * mask
            return jnp.sum(per_point), jnp.sum(mask)

        def mean_loss(params, *batch, rounds):
            total, count = loss_sums(params, *batch, rounds)
            return total / jnp.maximum(count, 1.0)

        def step(params, m, v, t, lr, *batch, rounds):
            loss, grads = jax.value_and_grad(mean_loss)(params, *batch, rounds=rounds)
            b1, b2, eps = 0.9, 0.999, 1e-7  # Keras Adam's defaults, as train-graph uses
            m = jax.tree_util.tree_map(lambda m_, g: b1 * m_ + (1 - b1) * g, m, grads)
            v = jax.tree_util.tree_map(lambda v_, g: b2 * v_ + (1 - b2) * g * g, v, grads)
            scale = lr * jnp.sqrt(1 - b2 ** t) / (1 - b1 ** t)
            params = jax.tree_util.tree_map(lambda p, m_, v_: p - scale * m_ / (jnp.sqrt(v_) + eps), params, m, v)
            return params, m, v, loss

        self._step = jax.jit(step, static_argnames="rounds")
        self._sums = jax.jit(loss_sums, static_argnames="rounds")
        self.t = 0

    def train_step(self, batch, fraction: float) -> list[float]:
        """One Adam step of every network; `fraction` of the budget spent sets the cosine rate."""
        self.t += 1
        lr = self.lr * 0.5 * (1 + np.cos(np.pi * min(fraction, 1.0)))
        batch = [self.jnp.asarray(x) for x in batch]
        losses = []
        for k, rounds in enumerate(self.rounds):
            m, v = self.moments[k]
            self.params[k], m, v, loss = self._step(self.params[k], m, v, float(self.t), float(lr), *batch,
                                                    rounds=rounds)
            self.moments[k] = (m, v)
            losses.append(loss)
        return [float(x) for x in losses]

    def validate(self, batches) -> list[float]:
        totals = np.zeros(len(self.rounds))
        count = 0.0
        for batch in batches:
            batch = [self.jnp.asarray(x) for x in batch]
            for k, rounds in enumerate(self.rounds):
                total, n = self._sums(self.params[k], *batch, rounds=rounds)
                totals[k] += float(total)
            count += float(n)
        return list(totals / count)

    def weights(self, k: int) -> dict[str, np.ndarray]:
        return {name: np.asarray(v, np.float32) for name, v in self.params[k].items()}


def _batches(gs: GraphSet, batch_steps: int, bucket: int, rng, scaling, stop: threading.Event,
             out: queue.Queue) -> None:
    """Fill `out` with shuffled padded batches, epoch after epoch, until `stop`."""
    while not stop.is_set():
        order = rng.permutation(len(gs))
        for k in range(0, len(order) - batch_steps + 1, batch_steps):  # loop over batches, not points
            if stop.is_set():
                return
            out.put(padded_batch(gs, np.sort(order[k:k + batch_steps]), *scaling, bucket=bucket))


def _scaling(train: GraphSet) -> tuple[dict, tuple[np.ndarray, ...]]:
    """The training set's normalization (as train-graph computes it) and its arrays
    (in_mean, in_std, out_mean, out_std), float32, as padded_batch takes them."""
    from training.train_graph import normalization

    norm = normalization([train])
    arrays = [np.array([norm[n][k] for n in names], np.float32)
              for names in (train.inputs, train.target_names) for k in (0, 1)]
    return norm, tuple(arrays)


def _train(probe: Probe, train: GraphSet, val_batches: list, scaling, args: argparse.Namespace):
    """Train every network of `probe` for args.seconds on batches that feeder threads
    draw from `train`, validating every args.val_every seconds. Returns (history per
    network: [seconds, steps, train loss, validation loss] rows; best per network:
    (validation loss, weights, seconds); Adam steps taken)."""
    history = [[] for _ in probe.names]
    best = [(np.inf, None, 0.0) for _ in probe.names]
    stop, ready = threading.Event(), queue.Queue(maxsize=32)
    feeders = [threading.Thread(target=_batches, daemon=True,
                                args=(train, args.batch_steps, args.point_bucket, np.random.default_rng(args.seed + k),
                                      scaling, stop, ready))
               for k in range(args.feeders)]
    for f in feeders:
        f.start()
    start, steps, next_val, losses = time.perf_counter(), 0, args.val_every, []
    while True:
        spent = time.perf_counter() - start
        losses.append(probe.train_step(ready.get(timeout=120), spent / args.seconds))
        steps += 1
        spent = time.perf_counter() - start
        if spent >= next_val or spent >= args.seconds:
            scores = probe.validate(val_batches)
            for k, score in enumerate(scores):
                history[k].append([round(spent, 1), steps, round(float(np.mean([x[k] for x in losses])), 6),
                                   round(score, 6)])
                if score < best[k][0]:
                    best[k] = (score, probe.weights(k), spent)
            losses = []
            print(f"{spent:6.0f} s, {steps} steps ({steps * args.batch_steps / len(train):.2f} epochs): "
                  + "  ".join(f"{n} val {s:.4f}" for n, s in zip(probe.names, scores)), flush=True)
            next_val += args.val_every
            if spent >= args.seconds:
                break
    stop.set()
    return history, best, steps


def run(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        train = concatenate(read_sets(args.train, None, args.workers, tmp))
        val = read_sets(args.val, VAL_STEPS, args.workers, tmp)
    read_seconds = time.perf_counter() - t0
    norm, scaling = _scaling(train)
    _, _, out_mean, out_std = scaling
    print(f"read {len(train)} training steps ({len(train.targets)} points) and "
          f"{sum(len(v) for v in val)} validation steps in {read_seconds:.0f} s", flush=True)

    probe = Probe(args.config, len(train.inputs), len(train.target_names), out_mean, out_std, args.lr, args.seed)
    val_batches = [padded_batch(v, np.arange(k, min(k + 64, len(v))), *scaling)
                   for v in val for k in range(0, len(v), 64)]
    # The loss of no correction: Box2D's own warm start.
    no_correction = float(sum(np.sum(np.square((0 - out_mean) / out_std - b[3]) * b[4][:, None]) for b in val_batches)
                          / sum(b[4].sum() for b in val_batches))
    history, best, steps = _train(probe, train, val_batches, scaling, args)
    for k, name in enumerate(probe.names):
        _save_npz(args.out / f"{name}.weights.npz", best[k][1])
    report = {
        "command": " ".join(sys.argv), "jax": probe.jax.__version__, "device": str(probe.jax.devices()[0]),
        "train": args.train, "val": args.val, "train_steps": len(train), "train_points": int(len(train.targets)),
        "val_steps": int(sum(len(v) for v in val)), "val_points": int(sum(len(v.targets) for v in val)),
        "read_seconds": round(read_seconds, 1), "train_seconds": args.seconds, "batch_steps": args.batch_steps,
        "lr": args.lr, "seed": args.seed, "normalization": norm, "loss": "mse", "loss_no_correction": no_correction,
        "steps": steps, "epochs": round(steps * args.batch_steps / len(train), 2),
        "networks": {name: {"width": w, "rounds": r, "layer_norm": norm, "best_loss": best[k][0], "best_at_seconds": round(best[k][2], 1),
                            "history": history[k]}
                     for k, (name, (w, r, norm)) in enumerate(zip(probe.names, args.config))},
    }
    _write_json(args.out / "probe.json", report)
    return 0


def _save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    part = path.with_name(f".{path.name}.part.npz")
    np.savez(part, **arrays)
    os.replace(part, path)


def _write_json(path: Path, obj) -> None:
    part = path.with_name(f".{path.name}.part")
    part.write_text(json.dumps(obj, indent=1))
    os.replace(part, path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab.train_graph_jax", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--train", action="append", required=True, help="recorded .h5 file (repeat; read in parallel)")
    p.add_argument("--val", action="append", required=True, help=f"validation .h5 file ({VAL_STEPS} steps each)")
    p.add_argument("--config", action="append", type=parse_config, required=True,
                   help="a network as WIDTHxROUNDS, e.g. 128x8, or 128x16n with a layer norm before each "
                        "round (repeat: trained side by side)")
    p.add_argument("--seconds", type=float, default=300.0, help="training budget, wall clock (default 300)")
    p.add_argument("--val-every", type=float, default=30.0, help="validate every this many seconds (default 30)")
    p.add_argument("--batch-steps", type=int, default=128, help="steps per batch (default 128)")
    p.add_argument("--lr", type=float, default=1e-3, help="peak Adam rate of the cosine schedule (default 1e-3)")
    p.add_argument("--point-bucket", type=int, default=POINT_BUCKET,
                   help=f"pad each batch's points to a multiple of this, so XLA compiles few shapes "
                        f"(default {POINT_BUCKET})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes reading files")
    p.add_argument("--feeders", type=int, default=4, help="threads building batches (default 4)")
    p.add_argument("--out", type=Path, required=True, help="folder for the weights and probe.json")
    args = p.parse_args(argv)
    missing = [x for x in args.train + args.val if not Path(x).exists()]
    if missing:
        print(f"train_graph_jax: no such file: {', '.join(missing)}", file=sys.stderr)
        return 2
    if importlib.util.find_spec("jax") is None:
        print("train_graph_jax: needs JAX, which is not one of deepcontact's dependencies: pip install jax "
              "(on a GPU machine, the CUDA build)", file=sys.stderr)
        return 2
    if args.seconds <= 0 or min(args.batch_steps, args.feeders, args.point_bucket) < 1:
        print("train_graph_jax: --seconds must be > 0, --batch-steps, --feeders and --point-bucket >= 1",
              file=sys.stderr)
        return 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
