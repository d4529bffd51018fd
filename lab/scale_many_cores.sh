#!/usr/bin/env bash
# The two scale questions docs/scale.md left open on a 16-core machine, in one run:
#   1. generate's ceiling per compression: gzip (the default), lzf and none, same seeds, same
#      worker count, and whether the three files hold the same simulations;
#   2. bench iterations at many workers against 1 and 4 server replicas, on a sweep long enough
#      that pool start-up is a small part, beside the same sweep without the server (builtin
#      alone), which is what the simulations cost by themselves.
#
# usage: bash lab/scale_many_cores.sh OUTDIR        (PY=python to use, default .venv/bin/python;
#        WORKERS (default: the machine's cores), GEN_SEEDS (default 1-256), IT_SEEDS (default 901-964),
#        REPEATS (default 2))
# Writes OUTDIR/generate.json and OUTDIR/iterations-*.json. Run where the cores are; see docs/scale.md.
set -euo pipefail

out=${1:?usage: bash lab/scale_many_cores.sh OUTDIR}
py=${PY:-.venv/bin/python}
workers=${WORKERS:-$(nproc)}
gen_seeds=${GEN_SEEDS:-1-256}
it_seeds=${IT_SEEDS:-901-964}
repeats=${REPEATS:-2}
mkdir -p "$out"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

echo "== generate --workers $workers --seeds $gen_seeds, per compression"
"$py" - "$tmp" "$out" "$gen_seeds" "$workers" <<'PYEOF'
import json, os, subprocess, sys, time
from deepcontact.io import write_json_atomic
from simclient.seeds import parse_seeds
from training.dataset import differences
tmp, out, spec, workers = sys.argv[1:5]
n = len(parse_seeds(spec))
runs = []
for c in ("gzip", "lzf", "none"):
    path = f"{tmp}/gen-{c}.h5"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "commands", "generate", "--quiet", "--seeds", spec, "--workers", workers,
                    "--compression", c, "--out", path], check=True)
    wall = time.perf_counter() - t0
    runs.append({"compression": c, "simulations": n, "wall_s": wall, "simulations_per_s": n / wall,
                 "mb_per_simulation": os.path.getsize(path) / n / 1e6, "load_1min": os.getloadavg()[0],
                 "same_as_gzip": not differences(f"{tmp}/gen-gzip.h5", path)})
    r = runs[-1]
    print(f"{c:5s} {wall:6.1f} s  {r['simulations_per_s']:5.1f}/s  {r['mb_per_simulation']:.2f} MB  "
          f"same as gzip: {r['same_as_gzip']}  load {r['load_1min']:.1f}", flush=True)
write_json_atomic(f"{out}/generate.json", {"workers": int(workers), "seeds": spec, "cores": os.cpu_count(), "runs": runs})
PYEOF

echo "== bench iterations --workers $workers --seeds $it_seeds: without the server, with 1 and 4 replicas"
"$py" -m commands bench scale --commands iterations --configs "workers=$workers" --repeats "$repeats" \
    --iteration-seeds "$it_seeds" --warm-starts builtin --json "$out/iterations-builtin.json"
for r in 1 4; do
    "$py" -m commands bench scale --commands iterations --configs "workers=$workers" --repeats "$repeats" \
        --replicas "$r" --iteration-seeds "$it_seeds" --warm-starts builtin,server:default \
        --json "$out/iterations-replicas$r.json"
done
