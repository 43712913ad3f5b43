#!/usr/bin/env bash
# Runs the experiments' programs on a lent GPU machine whose calls last at most 10 minutes:
# `start` launches the lanes of a plan in the background (each lane one shell command, the
# lanes side by side on the one GPU), `wait` watches them for up to N seconds and packs what
# they have made so far into $OUT/lease.tgz, so every call brings the finished cells back even
# if the machine is lost before the plan ends. tools/gpu/README.md gives the whole procedure.
#
#   bash tools/gpu/lease.sh setup [--tests]   install the carried wheels (.whl, .whltest)
#   bash tools/gpu/lease.sh start PLAN        launch PLAN's lanes (needs CCRJAX_COMMIT)
#   bash tools/gpu/lease.sh wait SECONDS      watch, then pack $OUT/lease.tgz
#   bash tools/gpu/lease.sh bench             `make bench` (before start: alone on the GPU)
#   bash tools/gpu/lease.sh tests             `make test` and `make train`
#   bash tools/gpu/lease.sh stop              end every lane
#
# A plan has one lane per line, `name: command`; `#` starts a comment. Each command runs from
# the repository root with $LANE_OUT naming its own results folder (under /tmp/lease/out/)
# and $PY the Python to use (the image's python3 unless PY names another).
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=/tmp/lease
SITE=/tmp/lease-site
export PY="${PY:-python3}"
OUT="${OUT:-$ROOT/pack}"
mkdir -p "$ROOT/lanes" "$ROOT/out" "$OUT"
export PYTHONPATH="$SITE:$PWD" PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# Lanes share the GPU: each takes memory as it needs it instead of 75% up front.
export XLA_PYTHON_CLIENT_PREALLOCATE=false

die() { echo "lease.sh: $*" >&2; exit 2; }

install_wheels() {  # folder, then the modules it provides
  local folder="$1"
  shift
  "$PY" -c "import $(IFS=,; echo "$*")" 2>/dev/null && return  # this Python has them
  [[ -d "$folder" ]] || die "$folder is missing: run tools/gpu/wheels.sh here and carry it"
  local stamp
  stamp="$SITE/.installed-$(ls "$folder" | md5sum | cut -c1-12)"
  [[ -f "$stamp" ]] && return
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$SITE" "$folder"/*.whl
  touch "$stamp"
}

# The two carried sets (tools/gpu/wheels.sh): what the experiments import, and what the
# tests and benchmarks import besides.
install_experiment_wheels() { install_wheels .whl rliable arch pandas brax; }
install_test_wheels() { install_wheels .whltest mpe2 flashbax pygame; }

setup() {
  install_experiment_wheels
  [[ "${1:-}" == "--tests" ]] && install_test_wheels
  "$PY" - <<'EOF'
import jax, flax, optax, orbax.checkpoint, pandas, rliable, sys
import ccrjax.envs.env  # brax, which the environment is built on
print("python", sys.version.split()[0], "| jax", jax.__version__, "| flax", flax.__version__,
      "| optax", optax.__version__, "| pandas", pandas.__version__)
print("devices:", jax.devices())
EOF
  nvidia-smi --query-gpu=name,memory.total,memory.used,driver_version --format=csv,noheader
}

running_lanes() {
  local pidfile
  for pidfile in "$ROOT"/lanes/*.pid; do
    [[ -e "$pidfile" ]] || continue
    local name
    name="$(basename "$pidfile" .pid)"
    # Running: no exit status written yet and its process group still alive (a lane killed
    # with its group never writes one).
    [[ -e "$ROOT/lanes/$name.rc" ]] || ! kill -0 -- "-$(cat "$pidfile")" 2>/dev/null \
      || echo "$name"
  done
}

start() {  # plan
  local plan="$1"
  [[ -f "$plan" ]] || die "no plan file $plan"
  [[ -n "${CCRJAX_COMMIT:-}" ]] || die "set CCRJAX_COMMIT to the commit of this tree \
(git rev-parse HEAD, here): the device's copy has no .git and every cell records its commit"
  [[ -z "$(running_lanes)" ]] || die "lanes still running: $(running_lanes | tr '\n' ' ')"
  install_experiment_wheels
  local line name command
  while IFS= read -r line || [[ -n "$line" ]]; do
    line="${line%%#*}"
    [[ "$line" =~ ^[[:space:]]*$ ]] && continue
    name="$(echo "${line%%:*}" | tr -d '[:space:]')"
    command="${line#*:}"
    [[ "$name" =~ ^[A-Za-z0-9_-]+$ ]] || die "lane name '$name' must be letters, digits, - or _"
    rm -f "$ROOT/lanes/$name".{rc,log,pid}
    mkdir -p "$ROOT/out/$name"
    LANE_OUT="$ROOT/out/$name" setsid nohup bash -c \
      "cd '$PWD'; export LANE_OUT='$ROOT/out/$name'; $command; echo \$? > '$ROOT/lanes/$name.rc'" \
      > "$ROOT/lanes/$name.log" 2>&1 < /dev/null &
    echo $! > "$ROOT/lanes/$name.pid"
    echo "lane $name started: $command"
  done < "$plan"
  cp "$plan" "$ROOT/plan"
}

report() {
  local log name state running
  # The running lanes, listed once: `running_lanes | grep -q` under pipefail reads a lane
  # that is running as "killed" when grep's early exit breaks the pipe of a longer list.
  running="$(running_lanes)"
  for log in "$ROOT"/lanes/*.log; do
    [[ -e "$log" ]] || continue
    name="$(basename "$log" .log)"
    if [[ -e "$ROOT/lanes/$name.rc" ]]; then state="exit $(cat "$ROOT/lanes/$name.rc")"
    elif grep -qx "$name" <<< "$running"; then state="running"
    else state="killed"; fi
    printf '%-12s %-9s %s\n' "$name" "$state" "$(tr '\r' '\n' < "$log" | grep -v '^\s*$' | tail -1 | cut -c1-160)"
  done
  nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null || true
}

pack() {
  # Everything made so far but the mid-program checkpoints (GBs; they die with the machine).
  tar czf "$OUT/lease.tgz" -C "$ROOT" --exclude=partial --exclude='*.pid' out lanes \
    $( [[ -e "$ROOT/plan" ]] && echo plan ) $( [[ -d "$ROOT/checks" ]] && echo checks )
  echo "packed $(du -h "$OUT/lease.tgz" | cut -f1) into \$OUT/lease.tgz"
}

wait_lanes() {  # seconds
  local deadline=$((SECONDS + $1))
  while [[ -n "$(running_lanes)" && $SECONDS -lt $deadline ]]; do sleep 10; done
  report
  pack
  [[ -z "$(running_lanes)" ]] && echo "all lanes ended" || echo "lanes running: $(running_lanes | tr '\n' ' ')"
}

bench() {
  # `make bench`, alone on the GPU (run it before `start`: lanes beside it would slow it).
  install_experiment_wheels
  install_test_wheels
  mkdir -p "$ROOT/checks"
  local bench name
  for bench in "env_throughput.py" "train_throughput.py --variants plain ccr" \
      "replay_compare.py"; do
    name="bench-${bench%%.py*}"
    # shellcheck disable=SC2086
    "$PY" benchmarks/$bench > "$ROOT/checks/$name.log" 2>&1 \
      && echo "$bench: done" || echo "$bench: FAILED"
    tail -14 "$ROOT/checks/$name.log"
  done
  pack
}

tests() {
  # What `make test` and `make train` run, with the image's python3 (the Makefile's targets
  # use a .venv that a machine without a package index cannot make). Their times are with
  # the lanes sharing the GPU, if any run.
  install_experiment_wheels
  install_test_wheels
  mkdir -p "$ROOT/checks"
  local t0
  t0=$SECONDS
  # -rfE names every failure in the log's last lines; the timeout keeps the call's margin.
  # At the limit it sends SIGABRT to pytest and its workers, whose fault handler (pytest
  # enables it) writes every thread's stack into the log: where a run that does not end
  # waits (on the H100 on 2026-11-26 all tests passed but pytest had not exited at 330 s).
  timeout -s ABRT -k 15 "${TESTS_TIMEOUT:-480}" "$PY" -m pytest -n 4 --dist loadfile -m "not slow" \
    -p no:cacheprovider -rfE --tb=line > "$ROOT/checks/test.log" 2>&1 && echo "make test: passed" || echo "make test: FAILED"
  echo "  $((SECONDS - t0)) s: $(tail -1 "$ROOT/checks/test.log")"
  t0=$SECONDS
  "$PY" -m ccrjax.train --scenario hidden_obstacle --algo maddpg --variant ccr --seeds 3 \
    --out "$ROOT/checks/train" > "$ROOT/checks/train.log" 2>&1 \
    && echo "make train: finished" || echo "make train: FAILED"
  echo "  $((SECONDS - t0)) s"
  tail -8 "$ROOT/checks/train.log"
  rm -rf "$ROOT/checks/train/checkpoints"
  [[ -n "$(running_lanes)" ]] && echo "(lanes were running beside: $(running_lanes | tr '\n' ' '))"
  pack
}

stop() {
  local pidfile
  for pidfile in "$ROOT"/lanes/*.pid; do
    [[ -e "$pidfile" ]] && kill -TERM -- "-$(cat "$pidfile")" 2>/dev/null || true
  done
  report
}

case "${1:-}" in
  setup) setup "${2:-}" ;;
  start) [[ $# -eq 2 ]] || die "usage: start PLAN"; start "$2" ;;
  wait) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "usage: wait SECONDS"; wait_lanes "$2" ;;
  bench) bench ;;
  tests) tests ;;
  stop) stop ;;
  *) die "usage: setup [--tests] | start PLAN | wait SECONDS | bench | tests | stop" ;;
esac
