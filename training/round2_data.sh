#!/usr/bin/env bash
# Data for the round-2 variants (docs/results.md, "Ablation"): the thesis world and the
# scene family, each step also solved from zero (--oracle) so oracle_* targets exist.
# Files are kept and reused; their names say what they hold.
#
#   bash training/round2_data.sh
set -euo pipefail
cd "$(dirname "$0")/.."
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
TRAIN_SEEDS=${TRAIN_SEEDS:-1-300}   # training range 1-799 (docs/data.md)
VAL_SEEDS=801-820                   # validation range 800-849
FAMILY=(--radius 0.3 0.55 --friction 0.2 0.8)

SECONDS=0
gen() { [ -f "$1" ] || "$DC" generate "${@:2}" --oracle --out "$1" --quiet; echo "$1 after ${SECONDS} s"; }
gen data/thesis-oracle-train-$TRAIN_SEEDS.h5 --scene thesis --seeds "$TRAIN_SEEDS"
gen data/family-oracle-train-$TRAIN_SEEDS.h5 --scene thesis "${FAMILY[@]}" --seeds "$TRAIN_SEEDS"
gen data/thesis-oracle-val-$VAL_SEEDS.h5 --scene thesis --seeds "$VAL_SEEDS"
gen data/family-oracle-val-$VAL_SEEDS.h5 --scene thesis "${FAMILY[@]}" --seeds "$VAL_SEEDS"
