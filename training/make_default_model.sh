#!/usr/bin/env bash
# The shipped default model, models/pressure.onnx + models/pressure.json, from nothing:
# thesis-scene data, training, ONNX export, evaluation on the validation seeds.
#
#   bash training/make_default_model.sh          (make default-model)
#
# Measured on the 2-core development machine: see docs/models.md.
# Data files are kept and reused (generation is deterministic and their names
# say what they hold); the run directory is always started afresh.
set -euo pipefail
cd "$(dirname "$0")/.."

DC=${DEEPCONTACT:-.venv/bin/deepcontact}
TRAIN_SEEDS=1-200           # training range 1-899 only (docs/data.md)
VAL_SEEDS=801-820           # other worlds than the training ones; never 900-999
TRAIN=data/thesis-train-$TRAIN_SEEDS.h5
VAL=data/thesis-val-$VAL_SEEDS.h5
RUN=runs/pressure
MODEL=models/pressure.onnx
# The default Pressure widths, with L2 0.0001 instead of the thesis's 0.01,
# which held the validation loss at 0.96-0.98 (0.79 with 0.0001) in a trial
# on seeds 1-40 (docs/models.md).
CONFIG='{"l2": 0.0001}'

SECONDS=0
[ -f "$TRAIN" ] || "$DC" generate --scene thesis --seeds "$TRAIN_SEEDS" --out "$TRAIN" --quiet
[ -f "$VAL" ] || "$DC" generate --scene thesis --seeds "$VAL_SEEDS" --out "$VAL" --quiet
echo "data ready after ${SECONDS} s"

rm -rf "$RUN"
"$DC" train --model pressure --train "$TRAIN" --val "$VAL" --out "$RUN" \
    --config "$CONFIG" --epochs 15 --patience 4 --batch-size 16 \
    --max-steps-per-file 10000 --max-val-steps 2000 --seed 0 --quiet
echo "trained after ${SECONDS} s"

"$DC" export "$RUN" --out "$MODEL"
"$DC" evaluate --model "$MODEL" --data "$VAL" --json "$RUN/eval.json"
ls -l "$MODEL" "${MODEL%.onnx}.json"
echo "done in ${SECONDS} s"
