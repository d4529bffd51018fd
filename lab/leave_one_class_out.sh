#!/usr/bin/env bash
# Leave one class out: the zoo's classifier trained without each class of the zoo and priced on
# that class, beside the same recipe trained on every class (docs/research/2026-12-06-a-zoo-of-worlds.md).
#
#   bash lab/leave_one_class_out.sh [CLASS ...]        (default: every class)
#
# The reduced recipe: one epoch of 10,000 steps of each file, from contact-modes' weights
# (python -m training.recover_weights models/contact-modes.json), the inputs and targets of
# training/zoo_model.sh, whose data it reads (run that first). Each classifier is served as the
# zoo route is (the default's face settings, contact-graph its fallback inside what that knows)
# and priced on Builtin's states of choosing seeds 850-854 of the left-out class:
# bench/results/loco-CLASS/. About 2 min of training and 20-40 s of pricing a class on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
STORE=${STORE:-lab/models}
DC=${DEEPCONTACT:-.venv/bin/deepcontact}
PY=${PYTHON:-.venv/bin/python}
ZOO="discs pyramid stack polygons jointed ragdolls terrain rotating"
INIT=runs/graph-cache/contact-modes.weights.npz
[ -f "$INIT" ] || "$PY" -m training.recover_weights models/contact-modes.json --out "$INIT"

train() {  # train OUT: every class but OUT ("all": every class)
    local c out=$1 files=(--train data/thesis-train-1-200.h5 --train data/family-train-1-200.h5
                        --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5)
    for c in $ZOO; do
        [ "$c" = "$out" ] && continue
        files+=(--train data/zoo/$c-train-1-200.h5 --val data/zoo/$c-val-801-810.h5)
    done
    [ -f $STORE/loco-without-$out.json ] || "$DC" train-graph "${files[@]}" --max-steps-per-file 10000 --max-val-steps 500 \
        --inputs scaled --targets face-labels --combine replace --extra-inputs friction --rounds 12 --loss mse \
        --init "$INIT" --epochs 1 --lr 5e-4 --patience 3 --seed 4 --quiet --out $STORE/loco-without-$out.onnx
}

train all
for c in ${@:-$ZOO}; do
    train "$c"
    # models/ and the two classifiers, each as a route with the default's face settings
    dir=runs/loco-models-$c
    rm -rf "$dir" && mkdir -p "$dir" && cp models/* "$dir"/
    "$PY" - "$dir" "$STORE" "$c" <<'EOF'
import json, shutil, sys
from pathlib import Path
folder, store, left_out = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
face = json.loads((folder / "default.json").read_text())["face"]
for alias, research in (("la", "loco-without-all"), ("lo", f"loco-without-{left_out}")):
    card = json.loads((store / f"{research}.json").read_text())
    card.update(name=f"{alias}-modes", onnx_file=f"{alias}-modes.onnx")
    shutil.copy(store / f"{research}.onnx", folder / f"{alias}-modes.onnx")
    (folder / f"{alias}-modes.json").write_text(json.dumps(card))
    (folder / f"{alias}.json").write_text(json.dumps({"name": alias, "alias_of": f"{alias}-modes",
                                                       "face": {**face, "fallback": "contact-graph"}}))
EOF
    "$DC" lab iterations --world simclient.zoo:$c --seeds 850-854 --workers 1 --no-guard --models "$dir" \
        --warm-starts builtin,price:server:la+server:lo --out bench/results/loco-$c --quiet
done
