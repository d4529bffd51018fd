#!/usr/bin/env bash
# The zoo's classifier on 500 simulations of each class in place of 200 (issue 100's data at
# scale): the recipe of training/zoo_model.sh, its files and 300 more of each class (seeds
# 201-500), the same two stages from the default's classifier's weights
# (docs/research/2026-12-06-a-zoo-of-worlds.md, "The zoo at 500 simulations a class").
#
#   bash lab/zoo_at_scale.sh            # after training/zoo_model.sh has made its data
#
# Measured on 2 AMD AVX-512 cores: the 2,400 simulations 344 s; training 660 s and about as much
# for the second stage (each card's training.train_seconds). Writes
# lab/models/graph-labels-scaled-zoo500-r12-e{2,4}; kept data files are reused.
set -euo pipefail
cd "$(dirname "$0")/.."
STORE=${STORE:-lab/models}
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
INIT=${INIT:-runs/graph-cache/graph-face-fr-r12-e15.weights.npz}
ZOO="discs pyramid stack polygons jointed ragdolls terrain rotating"
[ -f "$INIT" ] || { echo "zoo_at_scale.sh: $INIT is missing (see training/zoo_model.sh)" >&2; exit 2; }
for c in $ZOO; do
    [ -f data/zoo/$c-train-1-200.h5 ] || { echo "zoo_at_scale.sh: run training/zoo_model.sh first" >&2; exit 2; }
    [ -f data/zoo/$c-train-201-500.h5 ] || "$DC" generate --world simclient.zoo:$c --seeds 201-500 --steps 250 --workers 2 --out data/zoo/$c-train-201-500.h5 --quiet
done
FILES=(--train data/thesis-train-1-200.h5 --train data/family-train-1-200.h5
       --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5)
for c in $ZOO; do
    FILES+=(--train data/zoo/$c-train-1-200.h5 --train data/zoo/$c-train-201-500.h5 --val data/zoo/$c-val-801-810.h5)
done
RUN=(--max-steps-per-file 20000 --max-val-steps 1000 --inputs scaled --targets face-labels --combine replace
     --extra-inputs friction --rounds 12 --loss mse --lr 5e-4 --patience 3 --epochs 2 --quiet)
"$DC" train-graph "${FILES[@]}" "${RUN[@]}" --seed 3 --init "$INIT" --out $STORE/graph-labels-scaled-zoo500-r12-e2.onnx
"$DC" train-graph "${FILES[@]}" "${RUN[@]}" --seed 5 --init runs/graph-cache/graph-labels-scaled-zoo500-r12-e2.weights.npz \
    --out $STORE/graph-labels-scaled-zoo500-r12-e4.onnx
