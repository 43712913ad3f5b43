"""Peer throughput: JaxMARL's MPE ``simple_spread`` measured like our environment.

Same method as ``benchmarks/env_throughput.py``: 5 agents (and 5 landmarks, as
in the MPE's ``simple_spread``), continuous actions drawn uniformly inside one
jitted ``lax.scan``, the environment ``vmap``-ed over a batch of 1024, 4096 and
16384, through JaxMARL's full ``step`` (with its automatic reset), a compile and
warm-up run, then the median of ``--repeats`` timed rollouts. Episodes are 25
steps, like ours (``--episode-length``; JaxMARL's default too). JaxMARL's continuous action is 5
numbers in ``[0, 1]`` (none, -x, +x, -y, +y) that it turns into the force
``5 (a[2] - a[1], a[4] - a[3])``, so uniform draws give the same force
distribution as our uniform ``[-1, 1]^2`` actions would after differencing.

With ``--ippo FILE`` it times JaxMARL's IPPO training instead: ``FILE`` is
``baselines/IPPO/ippo_ff_mpe.py`` from a checkout of JaxMARL's repository (the pip package
has no baselines), whose ``make_train(config) -> train(key)`` is called as its own
``main`` calls it, at sizes matched to ccrjax's IPPO defaults: ``--ippo-envs`` training
environments (160), rollouts of one 25-step episode, 5 agents and 5 landmarks, 4 epochs of
4 minibatches, its 64-64 tanh actor and critic, one seed and three (``vmap`` over keys, as its
``main`` does; vmapped over 5 or more seeds it compiled, then deadlocked on a 2-core CPU with
jax 0.10.2, in the batched QR of its orthogonal initialisation); everything else as its
``ippo_ff_mpe.yaml`` sets it (discrete actions, a learning rate annealed over the run). It
imports ``hydra``, ``wandb`` and ``omegaconf`` for its command line and logging only; where
they are not installed, inert stand-ins take their place (its per-update ``io_callback``
still runs, into a ``wandb.log`` that does nothing).
The rate reported is environment steps per second of the whole training program: each timed
call trains ``--updates`` rollouts and updates, the median of ``--repeats`` after a compile
and warm-up call.

JaxMARL is never a dependency of ccrjax: this script runs in its own virtual
environment, ``benchmarks/.peer-venv``, which ``make bench-peers`` creates;
``benchmarks/ippo_versus_jaxmarl.py`` runs it beside ccrjax's IPPO and prints the ratio.

    benchmarks/.peer-venv/bin/python benchmarks/jaxmarl_peer.py [--json]
    benchmarks/.peer-venv/bin/python benchmarks/jaxmarl_peer.py --ippo FILE [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import json
import os
import statistics
import sys
import time
import types
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

import jax
import jax.numpy as jnp

SCENARIO = "jaxmarl_simple_spread"
DEFAULT_ENVS = (1024, 4096, 16384)
# ippo_ff_mpe.yaml's settings (JaxMARL's IPPO on the MPE), but for the sizes matched to
# ccrjax's IPPO defaults, which measure_ippo sets.
IPPO_CONFIG = {
    "LR": 2.5e-4, "UPDATE_EPOCHS": 4, "NUM_MINIBATCHES": 4, "GAMMA": 0.99,
    "GAE_LAMBDA": 0.95, "CLIP_EPS": 0.2, "ENT_COEF": 0.01, "VF_COEF": 0.5,
    "MAX_GRAD_NORM": 0.5, "ACTIVATION": "tanh", "ENV_NAME": "MPE_simple_spread_v3",
    "ANNEAL_LR": True,
}


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr, exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _int_at_least(low: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    """The command line of this benchmark."""
    parser = _Parser(prog="jaxmarl_peer.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", type=_int_at_least(1), default=list(DEFAULT_ENVS),
                        help="batch sizes (default: 1024 4096 16384)")
    parser.add_argument("--robots", type=_int_at_least(1), default=5,
                        help="agents (and landmarks) per environment (default: 5)")
    parser.add_argument("--steps", type=_int_at_least(1), default=100,
                        help="steps per timed rollout (default: 100, four episodes of 25)")
    parser.add_argument("--episode-length", type=_int_at_least(1), default=25,
                        help="JaxMARL's max_steps (default: 25, as ours)")
    parser.add_argument("--repeats", type=_int_at_least(1), default=5,
                        help="timed rollouts; the median is reported (default: 5)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per line instead of a table")
    parser.add_argument("--ippo", type=_existing_file, default=None, metavar="FILE",
                        help="time JaxMARL's IPPO training from this file (its repository's "
                        "baselines/IPPO/ippo_ff_mpe.py) instead of the environment")
    parser.add_argument("--ippo-envs", type=_int_at_least(1), default=160,
                        help="--ippo: training environments per seed (default: 160, "
                        "ccrjax's IPPO default)")
    parser.add_argument("--ippo-seeds", nargs="+", type=_int_at_least(1), default=[1, 3],
                        help="--ippo: seeds trained at once, one program each (default: 1 3)")
    parser.add_argument("--updates", type=_int_at_least(1), default=20,
                        help="--ippo: rollouts and updates per timed call (default: 20)")
    return parser


def _existing_file(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"must be a file, got {text!r} (JaxMARL's "
                                         "baselines/IPPO/ippo_ff_mpe.py)")
    return path


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silences file descriptor 1 (and ``sys.stdout``) for the duration.

    jaxmarl prints a notice about optional environments on import, and something
    it imports puts back the real ``sys.stdout`` under ``contextlib.redirect_stdout``,
    so the notice is silenced at the file-descriptor level; stdout stays JSON.
    """
    stdout = sys.stdout
    stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
        sys.stdout = stdout


def make_env(agents: int, episode_length: int) -> Any:
    """JaxMARL's ``MPE_simple_spread_v3`` with continuous actions."""
    with _quiet_stdout():
        from jaxmarl import make
        from jaxmarl.environments.mpe.default_params import CONTINUOUS_ACT
    return make("MPE_simple_spread_v3", num_agents=agents, num_landmarks=agents,
                action_type=CONTINUOUS_ACT, max_steps=episode_length)


def make_rollout(env: Any, envs: int, steps: int) -> Callable[[Any, jax.Array], Any]:
    """A jitted ``(state, key) -> state`` running ``steps`` random steps of ``envs`` envs."""
    step = jax.vmap(env.step)
    sizes = {agent: env.action_space(agent).shape for agent in env.agents}

    def body(carry: Any, key: jax.Array) -> tuple[Any, None]:
        state, total = carry
        step_key, *action_keys = jax.random.split(key, 1 + len(env.agents))
        actions = {
            agent: jax.random.uniform(k, (envs, *sizes[agent]))
            for agent, k in zip(env.agents, action_keys, strict=True)
        }
        obs, state, reward, done, info = step(jax.random.split(step_key, envs), state, actions)
        # Keep observations and rewards live, as our env.step returns them in its state.
        checksum = sum(jnp.sum(o) for o in obs.values()) + sum(
            jnp.sum(r) for r in reward.values()
        )
        return (state, total + checksum), None

    @jax.jit
    def rollout(carry: Any, key: jax.Array) -> Any:
        carry, _ = jax.lax.scan(body, carry, jax.random.split(key, steps))
        return carry

    return rollout


def measure(agents: int, envs: int, steps: int, episode_length: int,
            repeats: int) -> dict[str, Any]:
    """Times ``repeats`` rollouts after a compile-and-warm-up run; returns the result row."""
    env = make_env(agents, episode_length)
    rollout = make_rollout(env, envs, steps)
    key, reset_key = jax.random.split(jax.random.key(0))
    _, state = jax.vmap(env.reset)(jax.random.split(reset_key, envs))
    carry = (state, jnp.zeros(()))
    start = time.perf_counter()
    carry = jax.block_until_ready(rollout(carry, key))
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        key, run_key = jax.random.split(key)
        start = time.perf_counter()
        carry = jax.block_until_ready(rollout(carry, run_key))
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return {
        "scenario": SCENARIO,
        "robots": agents,
        "envs": envs,
        "env_steps_per_s": envs * steps / median,
        "ms_per_step": 1000.0 * median / steps,
        "median_s": median,
        "min_s": min(times),
        "steps": steps,
        "repeats": repeats,
        "warmup_s": warmup_s,
        "device": f"{jax.devices()[0].platform}:{jax.devices()[0].device_kind}",
        "jax": jax.__version__,
    }


def _inert_module(name: str) -> types.ModuleType:
    """A stand-in for ``hydra``, ``wandb`` or ``omegaconf``, which the IPPO script imports
    for its command line and logging only: what it touches does nothing."""
    module = types.ModuleType(name)
    module.main = lambda *args, **kwargs: (lambda function: function)  # hydra.main
    module.init = module.log = lambda *args, **kwargs: None  # wandb
    module.OmegaConf = types.SimpleNamespace(to_container=lambda config: config)
    return module


def load_ippo_make_train(path: Path) -> Callable[[dict[str, Any]], Callable]:
    """``make_train`` of JaxMARL's IPPO script at ``path``, imported as a module (its
    ``main`` is not run)."""
    for name in ("hydra", "wandb", "omegaconf"):
        if importlib.util.find_spec(name) is None:
            sys.modules[name] = _inert_module(name)
    spec = importlib.util.spec_from_file_location("jaxmarl_ippo_ff_mpe", path)
    module = importlib.util.module_from_spec(spec)
    with _quiet_stdout():
        spec.loader.exec_module(module)
    return module.make_train


def measure_ippo(make_train: Callable, agents: int, envs: int, episode_length: int,
                 updates: int, seeds: int, repeats: int) -> dict[str, Any]:
    """Times JaxMARL's whole IPPO training program of ``updates`` rollouts of ``envs``
    environments x ``episode_length`` steps, ``seeds`` seeds at once (vmap over keys, as
    its ``main``), the median of ``repeats`` calls after a compile-and-warm-up call."""
    steps = envs * episode_length * updates
    config = {**IPPO_CONFIG, "NUM_ENVS": envs, "NUM_STEPS": episode_length,
              "TOTAL_TIMESTEPS": steps,
              "ENV_KWARGS": {"num_agents": agents, "num_landmarks": agents,
                             "max_steps": episode_length}}
    with _quiet_stdout():
        train = make_train(dict(config))
    if seeds == 1:
        program, key = jax.jit(train), jax.random.PRNGKey(0)
    else:
        program = jax.jit(jax.vmap(train))
        key = jax.random.split(jax.random.PRNGKey(0), seeds)
    start = time.perf_counter()
    jax.block_until_ready(program(key))
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(program(key))
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return {
        "learner": "jaxmarl_ippo",
        "scenario": SCENARIO,
        "robots": agents,
        "num_envs": envs,
        "seeds": seeds,
        "updates": updates,
        "env_steps_per_s": steps / median,  # per seed
        "env_steps_per_s_all_seeds": seeds * steps / median,
        "median_s": median,
        "times_s": times,
        "repeats": repeats,
        "warmup_s": warmup_s,
        "device": f"{jax.devices()[0].platform}:{jax.devices()[0].device_kind}",
        "jax": jax.__version__,
    }


def main_ippo(args: argparse.Namespace) -> int:
    """``--ippo``: JaxMARL's IPPO training at each ``--ippo-seeds``."""
    make_train = load_ippo_make_train(args.ippo)
    rows = []
    for seeds in args.ippo_seeds:
        row = measure_ippo(make_train, args.robots, args.ippo_envs, args.episode_length,
                           args.updates, seeds, args.repeats)
        rows.append(row)
        if args.json:
            print(json.dumps(row), flush=True)
    if not args.json:
        print(f"JaxMARL IPPO (ippo_ff_mpe.py) on simple_spread, {args.robots} agents, "
              f"{args.ippo_envs} environments x {args.episode_length} steps per rollout, "
              f"{args.updates} updates per call, median of {args.repeats}; {rows[0]['device']}")
        for row in rows:
            print(f"{row['seeds']:>3} seed(s): {row['env_steps_per_s']:12,.0f} env steps/s per "
                  f"seed, {row['env_steps_per_s_all_seeds']:12,.0f} in all")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Runs every batch size; prints a table or JSON lines."""
    args = build_parser().parse_args(argv)
    if args.ippo is not None:
        return main_ippo(args)
    rows = []
    for envs in args.envs:
        row = measure(args.robots, envs, args.steps, args.episode_length, args.repeats)
        rows.append(row)
        if args.json:
            print(json.dumps(row), flush=True)
    if not args.json:
        print(f"JaxMARL simple_spread, random continuous actions, {args.steps} steps per "
              f"rollout, median of {args.repeats}; {rows[0]['device']}, jax {jax.__version__}")
        header = f"{'scenario':<22} {'robots':>6} {'envs':>7} {'env-steps/s':>14} {'ms/step':>9}"
        print(header)
        print("-" * len(header))
        for row in rows:
            print(f"{row['scenario']:<22} {row['robots']:>6d} {row['envs']:>7d} "
                  f"{row['env_steps_per_s']:>14,.0f} {row['ms_per_step']:>9.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
