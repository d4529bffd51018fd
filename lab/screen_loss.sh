#!/usr/bin/env bash
# The stopping-rule loss's settings, screened in iterations (docs/results.md, "The loss's
# settings, screened"): one epoch of the default's fine-tune (`--loss solver-projected-max`
# from graph-mse-1-799-e16's weights, 3,000 steps of each 1-799 file) per setting, each changing
# one thing from the control, then all of them priced in one run on Builtin's own states of
# the validation seeds (`price:server:*`), so every setting is compared step by step with the
# control. The whole per-state gain of that loss comes in its first epoch (docs/results.md, "On
# Builtin's states"), which is why one epoch is enough to screen.
#
#   bash lab/screen_loss.sh            (about 65 min on two cores)
#
# Needs the round-2 data (TRAIN_SEEDS=1-799 bash training/round2_data.sh) and
# runs/graph-cache/graph-mse-1-799-e16.weights.npz (bash training/round2_graph.sh
# graph-mse-1-799 graph-mse-1-799-e16, or python -m training.recover_weights
# models/graph-mse-1-799-e16.json). The screened models go to $OUT (runs/screen/, not
# shipped); a model already there is kept, so a stopped screen resumes.
set -euo pipefail
cd "$(dirname "$0")/.."
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
OUT=${OUT:-runs/screen}
SEEDS=${SEEDS:-800-849}   # validation seeds: the models stopped on 801-820's files, so not held out
INIT=runs/graph-cache/graph-mse-1-799-e16.weights.npz
COMMON=(--train data/thesis-train-1-799.h5 --train data/family-train-1-799.h5
        --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5 --max-val-steps 500 --seed 0 --quiet
        --max-steps-per-file 3000 --epochs 1 --lr 5e-4 --init "$INIT" --loss solver-projected-max)
# name|what it changes from the control (later flags override COMMON's)
SETTINGS=(
    "control|"
    "omega0.3|--omega 0.3"
    "sweeps-early|--sweeps 4,16,64"
    "sweeps-late|--sweeps 64,256"
    "tangent0.1|--tangent-weight 0.1"
    "norm2|--norm 2"
    "norm4|--norm 4"
    "lr1e-3|--lr 1e-3"
    "harm2|--harm-weight 2"
    "harm4|--harm-weight 4"
    "gauss-seidel|--order gauss-seidel"
)
[ -f "$INIT" ] || { echo "screen_loss.sh: $INIT is missing (see the header)" >&2; exit 2; }
mkdir -p "$OUT"
SECONDS=0
for setting in "${SETTINGS[@]}"; do
    name=screen-${setting%%|*}
    read -r -a flags <<< "${setting#*|}"
    if [ -f "$OUT/$name.onnx" ] && [ -f "$OUT/$name.json" ]; then
        echo "$name: kept from an earlier screen"
        continue
    fi
    start=$SECONDS
    "$DC" train-graph "${COMMON[@]}" "${flags[@]}" --out "$OUT/$name.onnx"
    echo "$name: trained in $((SECONDS - start)) s"
done
"$DC" lab iterations --models "$OUT" --seeds "$SEEDS" --workers 2 --deadline-ms 1000 \
    --warm-starts "builtin,price:server:*" --out bench/results/r2-screen-loss --quiet
echo "screen done in ${SECONDS} s"
