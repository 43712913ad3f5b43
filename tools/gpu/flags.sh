#!/usr/bin/env bash
# Does XLA's GPU command buffers (CUDA graphs) over whole loops speed up training?
# On the H100 an iteration is a loop of small kernels, so the GPU may wait on launches and on
# the loop's host round trips. Times benchmarks/train_throughput.py (MADDPG and MAAC, plain
# and CCR) under each flag set; the numbers are the same program's, so a faster set can be
# given to the lanes (XLA_FLAGS=... before `lease.sh start`). Run on the GPU machine after
# `lease.sh setup`. Measured on an H100 on 2026-11-24 (commit 907eea8): command buffers made
# every row slower (x0.91 to x0.98), so the lanes keep XLA's defaults.
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONPATH="/tmp/lease-site:$PWD" PYTHONUNBUFFERED=1
PY="${PY:-python3}"
CHECKS=/tmp/lease/checks
mkdir -p "$CHECKS"
CB="--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL"
for n in 0 1; do
  flags=""; [[ $n == 1 ]] && flags="$CB"
  echo "XLA_FLAGS='$flags'"
  XLA_FLAGS="$flags" timeout 200 "$PY" benchmarks/train_throughput.py --algos maac maddpg \
    --variants plain ccr --repeats 3 --json > "$CHECKS/flags$n.json" 2> "$CHECKS/flags$n.err" \
    || echo "  failed: $(tail -1 "$CHECKS/flags$n.err")"
  "$PY" -c "import json, sys
for line in open(sys.argv[1]):
    r = json.loads(line)
    print(f\"  {r['algo']:7} {r['variant']:6} {r['env_steps_per_s']:>10,.0f} env steps/s\")" \
    "$CHECKS/flags$n.json"
done
echo "fastest on every row: XLA_FLAGS='$("$PY" tools/gpu/pick_flags.py "$CHECKS/flags0.json" \
  "$CB" "$CHECKS/flags1.json")'"
