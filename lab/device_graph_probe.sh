#!/usr/bin/env bash
# "Far more training" (docs/results.md): on a machine with 16 cores and a GPU, no TensorFlow,
# Python 3.12, nothing fetched there. Generates round 2's training data (seeds 1-799 of the thesis
# world and the scene family, 16 files read in parallel) and the validation files, then trains
# contact-graph networks with JAX for SECONDS (lab/train_graph_jax.py). Writes to $OUT:
# probe.json, one NAME.weights.npz per network and log.txt. Carry .whl (the wheels: grpcio,
# h5py, protobuf, ... and .whl/box2d/, the patched Box2D built for 3.12),
# deepcontact/_transfer.cpython-312-x86_64-linux-gnu.so and _kinematics.cpython-312-x86_64-linux-gnu.so.
#
#   SECONDS_TRAIN=330 CONFIGS="128x3 128x8 256x8" bash lab/device_graph_probe.sh
set -u
SECONDS_TRAIN=${SECONDS_TRAIN:-330}
CONFIGS=${CONFIGS:-"128x3 128x8 256x8"}
CHUNKS=${CHUNKS:-"1-100 101-200 201-300 301-400 401-500 501-600 601-700 701-799"}  # training seeds, a file each
VAL=${VAL:-801-820}
BATCH_STEPS=${BATCH_STEPS:-512}
OUT=${OUT:-runs/device-probe}
mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
t0=$(date +%s)
python3 -m pip install -q --no-deps --no-index .whl/*.whl .whl/box2d/*.whl 2>&1 | tail -3
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
python3 -c "import Box2D, h5py, jax; print('imports ok;', jax.devices())" || exit 1
echo "setup $(( $(date +%s) - t0 )) s; cores $(nproc)"
D=/tmp/probe-data
mkdir -p $D
FAMILY=(--radius 0.3 0.55 --friction 0.2 0.8)
pids=()
gen() { python3 -m commands generate --scene thesis "${@:2}" --out "$D/$1.h5" --workers 1 --compression none --quiet & pids+=($!); }
for chunk in $CHUNKS; do
    gen thesis-train-$chunk --seeds $chunk
    gen family-train-$chunk --seeds $chunk "${FAMILY[@]}"
done
gen thesis-val-$VAL --seeds $VAL
gen family-val-$VAL --seeds $VAL "${FAMILY[@]}"
wait "${pids[@]}"  # not a bare wait: that would wait for the log's tee too
echo "data $(( $(date +%s) - t0 )) s: $(ls $D | wc -l) files, $(du -sh $D | cut -f1)"
cfg=(); for c in $CONFIGS; do cfg+=(--config "$c"); done
train=(); for f in $D/*-train-*.h5; do train+=(--train "$f"); done
python3 -m lab.train_graph_jax "${train[@]}" --val $D/thesis-val-$VAL.h5 --val $D/family-val-$VAL.h5 \
    "${cfg[@]}" --seconds "$SECONDS_TRAIN" --val-every 30 --batch-steps "$BATCH_STEPS" --lr 2e-3 --feeders 6 --out "$OUT"
echo "total $(( $(date +%s) - t0 )) s"
