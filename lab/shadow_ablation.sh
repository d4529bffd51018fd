#!/usr/bin/env bash
# The ablation's same-state column (docs/results.md, "The ablation"): the default when it was
# measured (graph-projected-max-1-799-long-e2, named here so that the column reproduces after
# the default moved on) served on the thesis world's reporting seeds 901-950, and every other model of the table
# priced on the very same states by the engine's trial solves (`shadow:`), in three runs of
# about twenty models each (a run's every step costs one solve per candidate).
#
#   bash lab/shadow_ablation.sh [OUT_PREFIX]     (default bench/results/r2-shadow-ablation)
#
# Writes OUT_PREFIX-0, -1, -2 (summary.json: "picks", results.md: the per-candidate table).
# About 20-30 min a run on two cores.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-bench/results/r2-shadow-ablation}
deepcontact=${DEEPCONTACT:-.venv/bin/deepcontact}

batches=(
  "pressure pressure-new-points residual residual-new-points points-residual points-residual-new-points
   points-residual-contact points-residual-contact-new-points unet-residual-contact unet-residual-contact-new-points
   graph-mse graph-mse-t0.3 graph-solver graph-solver-t1 graph-solver-new-points graph-solver-r6 graph-solver-r6-t1
   graph-relative graph-mse-1-799 graph-mse-1-799-t0.3 graph-mse-1-799-e16 graph-mse-1-799-e16-t0.3
   graph-projected-1-799"
  "graph-projected-1-799-t1 graph-projected-1-799-s20k graph-projected-1-799-s20k-t1 graph-projected-max-1-799
   graph-projected-max-1-799-t1 graph-projected-max-1-799-t0.3 graph-projected-max-1-799-t2
   graph-projected-max-1-799-seed1 graph-projected-max-1-799-seed1-t1 graph-projected-max-1-799-seed2
   graph-projected-max-1-799-seed2-t1 graph-projected-max-1-799-seed2-long graph-projected-max-1-799-seed2-long-t1
   graph-projected-max-1-799-e4 graph-projected-max-1-799-e4-t1 graph-projected-max-1-799-long
   graph-projected-max-1-799-long-t1 graph-projected-max-1-799-pooled-long graph-projected-max-1-799-pooled-long-t1
   graph-projected-max-1-799-long-e2-t1 graph-projected-max-1-799-long-e2-x1.25 graph-projected-max-1-799-long-e2-x0.8
   graph-projected-max-1-799-long-e3"
  "graph-projected-max-1-799-long-e3-t1 graph-ensemble-e2-e3 graph-ensemble3 graph-ensemble3-t1 graph-ensemble-long-e2
   graph-ensemble-long-e2-t1 graph-agree3-k0.2 graph-agree3-k0.35 graph-projected-max-1-799-pooled
   graph-projected-max-1-799-pooled-t1 graph-projected-max-1-799-pooled-e4 graph-projected-max-1-799-pooled-e4-t1
   graph-projected-max-w32 graph-projected-max-w32-t1 graph-projected-max-w64 graph-projected-max-w64-t1
   graph-oracle-mse graph-oracle-mse-t0.3 graph-oracle-mse-t1 graph-final-mse-o200 graph-final-mse-o200-t0.3
   graph-final-mse-o200-t1"
)

for i in "${!batches[@]}"; do
  candidates=server:graph-projected-max-1-799-long-e2
  for model in ${batches[$i]}; do  # word splitting on purpose: one model name per word
    candidates+="+server:$model"
  done
  "$deepcontact" lab iterations --seeds 901-950 --workers 2 --deadline-ms 1000 \
    --warm-starts "builtin,shadow:$candidates" --out "$out-$i"
done
