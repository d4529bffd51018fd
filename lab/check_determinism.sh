#!/usr/bin/env bash
# Does a training run give the same weights twice on this machine, under load, and with
# TensorFlow's CPU kernels held to other instructions? (docs/models.md, "The shipped models")
#
#   bash lab/check_determinism.sh          # 14 min on 2 cores shared with a training run (measured); less alone
#
# One short train-graph run (6 thesis-world simulations, the default's loss, 2 epochs), six ways:
#   again       the same command a second time
#   busy        while three shell loops keep every core busy
#   avx2        ONEDNN_MAX_CPU_ISA=AVX2: oneDNN's kernels as on a CPU without AVX-512
#   no-onednn   TF_ENABLE_ONEDNN_OPTS=0: TensorFlow's own kernels instead of oneDNN's
#   one-cpu     taskset -c 0: TensorFlow sees one CPU, so its thread pools split work otherwise
# Prints each one's largest weight difference from the first run. Writes only under a
# temporary folder, removed at the end.
set -euo pipefail
cd "$(dirname "$0")/.."
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
PY=${PYTHON:-.venv/bin/python}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"; kill $(jobs -p) 2>/dev/null || true' EXIT

"$DC" generate --scene thesis --seeds 1-6 --out "$TMP/train.h5" --quiet > /dev/null
"$DC" generate --scene thesis --seeds 801-802 --out "$TMP/val.h5" --quiet > /dev/null
train() {  # NAME [PREFIX...]: one short run, its weights left in $TMP/NAME/cache/m.weights.npz
    local name=$1; shift
    "$@" "$DC" train-graph --train "$TMP/train.h5" --val "$TMP/val.h5" --out "$TMP/$name/m.onnx" --cache "$TMP/$name/cache" \
        --loss solver-projected-max --sweeps 16,64 --epochs 2 --lr 5e-4 --seed 0 --quiet > "$TMP/$name.log"
    echo "$name: trained" >&2
}

train first
train again
for _ in 1 2 3; do (while :; do :; done) & done
train busy
kill $(jobs -p) 2>/dev/null || true
ONEDNN_MAX_CPU_ISA=AVX2 train avx2
TF_ENABLE_ONEDNN_OPTS=0 train no-onednn
train one-cpu taskset -c 0

"$PY" - "$TMP" <<'EOF'
import sys
from pathlib import Path

import numpy as np

tmp = Path(sys.argv[1])
first = np.load(tmp / "first/cache/m.weights.npz")
print("| run | largest weight difference from the first |\n|---|---|")
for name in ("again", "busy", "avx2", "no-onednn", "one-cpu"):
    other = np.load(tmp / name / "cache/m.weights.npz")
    print(f"| {name} | {max(float(np.max(np.abs(first[k] - other[k]))) for k in first.files):.3g} |")
EOF
