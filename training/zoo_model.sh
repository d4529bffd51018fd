#!/usr/bin/env bash
# The classifier of the zoo (models/contact-modes-zoo), from the default's classifier's weights:
# make default-model runs it after the default's classifier; alone it needs
# runs/graph-cache/graph-face-fr-r12-e15.weights.npz (python -m training.recover_weights
# models/contact-modes.json --out that path recovers it from the shipped file).
#
#   bash training/zoo_model.sh
#
# Data: 200 simulations of each class of the zoo (simclient/zoo.py) and of the thesis world and
# the scene family, 10 validation simulations of each class (801-810) and 20 of each project world
# (801-820): about 6 min on 2 cores (the zoo 4 min 10 s, the thesis and family files 64 s and 51 s,
# 2 AMD AVX-512 cores). Training: the same network as contact-modes (twelve rounds, each point's
# friction an input) on the channels in the step's own units (--inputs scaled) to the recorded
# face (--targets face-labels): 2 epochs of 20,000 steps a file, and 2 more from their weights, another
# draw: 382 s and 362 s of training on 2 AMD AVX-512 cores, 827 s in all with reading the files
# (each card's training.train_seconds).
# Kept data files are reused; the runs start afresh.
#
#   SIMS=500 bash training/zoo_model.sh
#
# trains the same on 500 simulations of each class (seeds 201-500 in a second file of each; 344 s
# of data, 660 s and 654 s of training), as graph-labels-scaled-zoo500-r12-e{2,4}: not kept
# (docs/research/2026-12-06-a-zoo-of-worlds.md, "The zoo at 500 simulations a class").
set -euo pipefail
cd "$(dirname "$0")/.."
STORE=${STORE:-lab/models}
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
INIT=${INIT:-runs/graph-cache/graph-face-fr-r12-e15.weights.npz}
ZOO="discs pyramid stack polygons jointed ragdolls terrain rotating"
SIMS=${SIMS:-200}
NAME=graph-labels-scaled-zoo$([ "$SIMS" = 200 ] || echo "$SIMS")-r12
FAMILY=(--radius 0.3 0.55 --friction 0.2 0.8)
mkdir -p data/zoo "$STORE"
[ -f "$INIT" ] || { echo "zoo_model.sh: $INIT is missing (see the head of this script)" >&2; exit 2; }

SECONDS=0
for c in $ZOO; do
    [ -f data/zoo/$c-train-1-200.h5 ] || "$DC" generate --world simclient.zoo:$c --seeds 1-200 --steps 250 --workers 2 --out data/zoo/$c-train-1-200.h5 --quiet
    [ -f data/zoo/$c-val-801-810.h5 ] || "$DC" generate --world simclient.zoo:$c --seeds 801-810 --steps 250 --workers 2 --out data/zoo/$c-val-801-810.h5 --quiet
    [ "$SIMS" = 200 ] || [ -f data/zoo/$c-train-201-$SIMS.h5 ] || "$DC" generate --world simclient.zoo:$c --seeds 201-$SIMS --steps 250 --workers 2 --out data/zoo/$c-train-201-$SIMS.h5 --quiet
done
[ -f data/thesis-train-1-200.h5 ] || "$DC" generate --scene thesis --seeds 1-200 --workers 2 --out data/thesis-train-1-200.h5 --quiet
[ -f data/family-train-1-200.h5 ] || "$DC" generate --scene thesis "${FAMILY[@]}" --seeds 1-200 --workers 2 --out data/family-train-1-200.h5 --quiet
[ -f data/thesis-val-801-820.h5 ] || "$DC" generate --scene thesis --seeds 801-820 --workers 2 --out data/thesis-val-801-820.h5 --quiet
[ -f data/family-val-801-820.h5 ] || "$DC" generate --scene thesis "${FAMILY[@]}" --seeds 801-820 --workers 2 --out data/family-val-801-820.h5 --quiet
echo "zoo data ready after ${SECONDS} s"

FILES=(--train data/thesis-train-1-200.h5 --train data/family-train-1-200.h5
       --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5)
for c in $ZOO; do
    FILES+=(--train data/zoo/$c-train-1-200.h5 --val data/zoo/$c-val-801-810.h5)
    [ "$SIMS" = 200 ] || FILES+=(--train data/zoo/$c-train-201-$SIMS.h5)
done
RUN=(--max-steps-per-file 20000 --max-val-steps 1000 --inputs scaled --targets face-labels --combine replace
     --extra-inputs friction --rounds 12 --loss mse --lr 5e-4 --patience 3 --epochs 2 --quiet)
"$DC" train-graph "${FILES[@]}" "${RUN[@]}" --seed 3 --init "$INIT" --out $STORE/$NAME-e2.onnx
"$DC" train-graph "${FILES[@]}" "${RUN[@]}" --seed 5 --init runs/graph-cache/$NAME-e2.weights.npz --out $STORE/$NAME-e4.onnx
echo "$NAME-e4 trained after ${SECONDS} s"
