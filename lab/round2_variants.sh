#!/usr/bin/env bash
# The round-2 variants of the ablation (docs/results.md): each trained on the thesis
# world and the scene family together (training/round2_data.sh; ORACLE=1 for the oracle variant), exported with its
# card to models/ (served like the shipped ones), and, where the model predicts a correction, also
# carded as "-new-points" (same ONNX, applied only to points new this step).
#
#   bash lab/round2_variants.sh [VARIANT ...]     (default: all)
#
# Then: deepcontact bench iterations --warm-starts builtin,server:NAME,...
set -euo pipefail
cd "$(dirname "$0")/.."
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
PY=${PYTHON:-.venv/bin/python}
TRAIN_SEEDS=${TRAIN_SEEDS:-1-300}
DATA=(--train data/thesis-train-$TRAIN_SEEDS.h5 --train data/family-train-$TRAIN_SEEDS.h5
      --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5)
ORACLE_SEEDS=${ORACLE_SEEDS:-1-60}  # oracle targets: smaller files (ORACLE=1 bash training/round2_data.sh)
ORACLE_DATA=(--train data/thesis-oracle-train-$ORACLE_SEEDS.h5 --train data/family-oracle-train-$ORACLE_SEEDS.h5
             --val data/thesis-oracle-val-801-806.h5 --val data/family-oracle-val-801-806.h5)
COMMON=(--epochs 10 --patience 3 --batch-size 16 --max-steps-per-file 5000 --max-val-steps 1000 --seed 0
        --config '{"l2": 0.0001}' --quiet)
BASE=mass,vx,vy,omega,normal_x,normal_y,builtin_normal,builtin_tangent
CONTACT=vn,vt,separation,new_point,previous_builtin_normal,previous_builtin_tangent
OUT=models
mkdir -p "$OUT"


variant() {  # NAME TRAIN-ARGS... (the data: DATA, or ORACLE_DATA when the first is --oracle-data)
    local name=$1; shift
    local data=("${DATA[@]}")
    if [ "${1:-}" = --oracle-data ]; then data=("${ORACLE_DATA[@]}"); shift; fi
    SECONDS=0
    rm -rf "runs/$name"
    "$DC" train "${data[@]}" "${COMMON[@]}" --out "runs/$name" "$@"
    "$DC" export "runs/$name" --out "$OUT/$name.onnx"
    "$PY" -m training.card_variant "$OUT/$name.json" --combine new-points
    echo "$name: trained and exported in ${SECONDS} s"
}

run() {
    case $1 in
    # The loss at the contact points (G2P in the graph), Box2D's warm start as input, correction as target.
    points-residual) variant $1 --model pressure --inputs $BASE --targets correction_normal,correction_tangent ;;
    # ... plus contact kinematics (relative velocity, separation, novelty) and last step's impulses.
    points-residual-contact) variant $1 --model pressure --inputs $BASE,$CONTACT \
        --targets correction_normal,correction_tangent ;;
    # ... the target is the oracle (this step solved from zero) minus builtin, not the final impulse.
    oracle-residual-contact) variant $1 --oracle-data --model pressure --inputs $BASE,$CONTACT \
        --targets oracle_correction_normal,oracle_correction_tangent ;;
    # Capacity: Tirca's encoder-decoder with skips, same inputs and targets as points-residual-contact.
    unet-residual-contact) variant $1 --model unet --inputs $BASE,$CONTACT \
        --targets correction_normal,correction_tangent ;;
    # The correction shrunk (a card variant, no training): builtin + 0.5 or 0.25 x the correction.
    shrink) for scale in 0.5 0.25; do
                "$PY" -m training.card_variant "$OUT/points-residual-contact.json" --correction-scale $scale
            done ;;
    *) echo "unknown variant $1" >&2; exit 2 ;;
    esac
}

VARIANTS=("$@")
[ ${#VARIANTS[@]} -gt 0 ] || VARIANTS=(points-residual points-residual-contact shrink unet-residual-contact
                                     oracle-residual-contact)
for v in "${VARIANTS[@]}"; do run "$v"; done
