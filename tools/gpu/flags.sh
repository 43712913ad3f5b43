#!/usr/bin/env bash
# Does XLA's GPU command buffers (CUDA graphs) over whole loops speed up training?
# On the H100 an iteration is a loop of small kernels (a few hundred environments per
# program), so the GPU waits on launches and on the loop's host round trips: CCR's extra
# small operations made a step about 5 times dearer there, against 1.1 times on the CPU.
# Times benchmarks/train_throughput.py (MADDPG and MAAC, plain and CCR) under each flag set;
# the numbers are the same program's, so a faster set can be given to the lanes
# (XLA_FLAGS=... before `lease.sh start`). Run on the GPU machine after `lease.sh setup`.
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONPATH="/tmp/lease-site:$PWD" PYTHONUNBUFFERED=1
PY="${PY:-python3}"
for flags in "" \
    "--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL" \
    "--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL --xla_gpu_graph_min_graph_size=1"; do
  echo "XLA_FLAGS='$flags'"
  XLA_FLAGS="$flags" timeout 240 "$PY" benchmarks/train_throughput.py --algos maddpg maac \
    --variants plain ccr --repeats 5 2>&1 | grep -E "^(maddpg|maac) |rror" || echo "  failed"
done
