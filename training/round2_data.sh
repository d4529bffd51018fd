#!/usr/bin/env bash
# Data for the round-2 variants (docs/results.md, "Ablation"): the thesis world and the
# scene family. Files are kept and reused; their names say what they hold.
#
#   bash training/round2_data.sh            the records (about 1 s per simulation and core)
#   ORACLE=1 bash training/round2_data.sh   also smaller files with each step solved from
#                                           zero (--oracle, for oracle_* targets; about
#                                           ten times as long)
set -euo pipefail
cd "$(dirname "$0")/.."
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
TRAIN_SEEDS=${TRAIN_SEEDS:-1-300}   # training range 1-799 (docs/data.md)
VAL_SEEDS=801-820                   # validation range 800-849
FAMILY=(--radius 0.3 0.55 --friction 0.2 0.8)

SECONDS=0
gen() { [ -f "$1" ] || "$DC" generate "${@:2}" --out "$1" --quiet; echo "$1 after ${SECONDS} s"; }
if [ "${ORACLE:-0}" = 1 ]; then
    ORACLE_SEEDS=${ORACLE_SEEDS:-1-60}
    gen data/thesis-oracle-train-$ORACLE_SEEDS.h5 --scene thesis --seeds "$ORACLE_SEEDS" --oracle
    gen data/family-oracle-train-$ORACLE_SEEDS.h5 --scene thesis "${FAMILY[@]}" --seeds "$ORACLE_SEEDS" --oracle
    gen data/thesis-oracle-val-801-806.h5 --scene thesis --seeds 801-806 --oracle
    gen data/family-oracle-val-801-806.h5 --scene thesis "${FAMILY[@]}" --seeds 801-806 --oracle
else
    gen data/thesis-train-$TRAIN_SEEDS.h5 --scene thesis --seeds "$TRAIN_SEEDS"
    gen data/family-train-$TRAIN_SEEDS.h5 --scene thesis "${FAMILY[@]}" --seeds "$TRAIN_SEEDS"
    gen data/thesis-val-$VAL_SEEDS.h5 --scene thesis --seeds "$VAL_SEEDS"
    gen data/family-val-$VAL_SEEDS.h5 --scene thesis "${FAMILY[@]}" --seeds "$VAL_SEEDS"
fi
