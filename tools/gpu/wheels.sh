#!/usr/bin/env bash
# Fills .whl/ with the Python 3.12 x86-64 wheels that the lent GPU machine's image lacks and
# the experiments need (rliable and arch for the statistics; pandas < 3, which arch 7 needs;
# brax and MuJoCo, since ccrjax's environment is a brax Env), and, with --tests, .whltest/
# with those that only the test suite and the benchmarks need (mpe2 and PettingZoo,
# flashbax). Run it here, where pip reaches a package index; the GPU machine reaches none. Both folders are git-ignored and travel with a call's
# `carry` (64 MiB in all, the working tree included).
#
# The image's own packages (jax with CUDA, flax, optax, chex, orbax-checkpoint, numpy, scipy,
# matplotlib, ...) are used as they are; tools/gpu/README.md lists what was checked there.
set -euo pipefail
cd "$(dirname "$0")/../.."
PIP="${PIP:-.venv/bin/python -m pip}"
PLATFORM=(--only-binary=:all: --python-version 3.12 --implementation cp
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64
  --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64)

# The experiments: named one by one with --no-deps, so nothing the image has comes twice.
rm -rf .whl && mkdir -p .whl
# rliable publishes no wheel: build its pure-Python one here.
$PIP wheel -q --no-deps -w .whl "rliable==1.2.0"
# arch's needs, then brax's that the image lacks; brax's rendering extras are left out
# (mujoco's viewer and OpenGL are never imported).
$PIP download -q --no-deps "${PLATFORM[@]}" -d .whl \
  "arch>=5.3.1,<8" "pandas>=2,<3" pytz tzdata \
  "brax==0.14.2" "mujoco==4.0.0" "mujoco-core==4.0.0" "mujoco-mjx==3.17.0" jaxopt \
  ml_collections trimesh flask flask_cors blinker itsdangerous tensorboardX

if [[ "${1:-}" == "--tests" ]]; then
  rm -rf .whltest && mkdir -p .whltest
  # mpe2's needs that the image lacks, pygame among them: mpe2's environments import it when
  # they load (mpe2/_mpe_utils/simple_env.py), which two tests of tests/test_world.py met on
  # the H100 on 2026-11-26.
  $PIP download -q --no-deps "${PLATFORM[@]}" -d .whltest \
    "mpe2==1.1.1" pettingzoo gymnasium farama-notifications pygame "flashbax==0.1.3"
fi
du -sh .whl .whltest 2>/dev/null || true
