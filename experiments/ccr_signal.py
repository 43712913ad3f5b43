"""Is CCR's signal about emergencies? ``python experiments/ccr_signal.py``.

    python experiments/ccr_signal.py                        # 512 episodes per scenario
    python experiments/ccr_signal.py --episodes 32 --out /tmp/s   # small, for the tests

CCR's emergency score is the error of a learned model of nominal motion; anything the
model cannot predict raises it, robot-robot contacts as much as hazards. For CCR's
intrinsic reward to be about emergencies, most of it must arise near hazards. Under a
reference controller (the hazard-blind go-to-goal of ``reference_controllers.py``, which
heads for the target as a plain learner does), or under a plain learner trained first in
the same scenario (``--trained maddpg``), per scenario, this measures:

* the smoothed emergency score ``E`` of robots in danger, in robot-robot contact
  (centres closer than two radii plus ``CONTACT_SLACK``) but not in danger, and in free
  motion (neither): quartiles and means;
* the **share of the intrinsic reward's magnitude** ``sum |R_in|`` that arises within
  ``m`` steps of a robot of the same environment being in danger (any robot of that
  environment in danger at one of the steps ``t - m, ..., t + 1`` of the transition
  ``t -> t + 1``; ``m`` is CCR's rolling-mean window);
* the **share of dangerous robot-steps that a teammate's danger forewarned**: steps of a
  spell of danger (consecutive dangerous steps of one robot) that began while the robot,
  itself safe, had a teammate in danger within communication range, or had had one at most
  ``m`` steps earlier (:func:`forewarning`), by a lead of at least 1, 2, 3 and 5 steps, and
  the median lead. It says how much warning the policy measured leaves to CCR's reflex (a
  follower turning away because a teammate ahead is in trouble), not what CCR does: CCR's
  reward also acts on robots already in danger, and training with it changes the policy.

CCR's model is first fitted as in training, where the learners' first ``learning_starts``
transitions come from uniformly random actions: on ``--warmup`` episodes of random
actions in the same scenario (its statistics are taken in at each episode's end); then
one batch of ``--episodes`` episodes of the controller is measured with lambda = 1 (the
share does not depend on lambda).

``--matmul tf32`` measures the same with CCR's model computed as on a GPU: there JAX's
default precision multiplies float32 matrices in TensorFloat32 (operands rounded to 10-bit
mantissas, products summed in float32), which this CPU cannot do, so every matrix product
of the model (its predictions and its fit's statistics) gets its operands rounded so first
(:func:`tf32_model_products`).
Writes ``<out>/ccr_signal.json`` and ``ccr_signal.md``.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/ccr_signal.py")

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ccrjax import cli
from ccrjax.envs.env import EmergencyEnv
from ccrjax.run.folder import git_commit, write_atomic
from ccrjax.training import TrainConfig, make_train
from ccrjax.training.acting import run_episode
from ccrjax.transforms.ccr import dynamics, transform
from ccrjax.transforms.ccr.transform import CCR
from experiments.ledger import add_out_options, prepare_out
from experiments.reference_controllers import CONTROLLERS

SCENARIOS = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")
CONTACT_SLACK = 0.01
TARGET_SHARE = 0.70
PROG = "python experiments/ccr_signal.py"
TRAIN_STEPS = 150_000  # --trained's default training budget
MATMULS = ("float32", "tf32")
WINDOW = CCR().config.window  # m, as measured (CCR's default configuration)
FOREWARNING_LEADS = (1, 2, 3, 5)  # steps of lead whose shares are reported


def round_to_tf32(x: jax.Array) -> jax.Array:
    """``x`` (float32) rounded to TensorFloat32's 10 mantissa bits, to nearest, ties to even."""
    bits = jax.lax.bitcast_convert_type(jnp.asarray(x, jnp.float32), jnp.uint32)
    bits = bits + jnp.uint32(0x0FFF) + ((bits >> 13) & jnp.uint32(1))
    return jax.lax.bitcast_convert_type(bits & jnp.uint32(0xFFFFE000), jnp.float32)


@contextlib.contextmanager
def tf32_model_products():
    """Within it, the matrix products of CCR's model (``jnp.einsum`` in
    :mod:`ccrjax.transforms.ccr.dynamics` and :mod:`~ccrjax.transforms.ccr.transform`, the
    only ones it has) take their operands rounded to TensorFloat32, as a GPU's tensor cores
    do under JAX's default precision. Programs must be traced inside it."""
    modules = (dynamics, transform)
    originals = [module.jnp for module in modules]
    emulated = SimpleNamespace(**vars(jnp))
    emulated.einsum = lambda spec, *operands, **kwargs: jnp.einsum(
        spec, *[round_to_tf32(operand) for operand in operands], **kwargs)
    for module in modules:
        module.jnp = emulated
    try:
        yield
    finally:
        for module, original in zip(modules, originals, strict=True):
            module.jnp = original


def trained_policy(scenario: str, algo: str, steps: int, seed: int):
    """A plain ``algo`` learner trained ``steps`` environment steps in ``scenario``: its
    deterministic policy on the plain observation features, and its final evaluation."""
    config = TrainConfig(algo=algo, scenario=scenario, variant="plain", total_env_steps=steps,
                         eval_every=steps)
    program = make_train(config)
    state, history = jax.jit(program.train)(jax.random.PRNGKey(seed + 1000))
    features = program.env.observation_size

    def act(obs, key):
        return program.learner.act(state.learner, obs[..., :features], key, False)

    final = {name: float(values[-1]) for name, values in history.items()}
    return act, final


def measure(scenario: str, controller: str, episodes: int, warmup: int,
            seed: int, trained: str | None = None, train_steps: int = 0) -> dict[str, Any]:
    """The score distributions and the intrinsic reward's share near danger, one scenario."""
    env = EmergencyEnv(scenario, num_envs=episodes)
    transform = CCR()
    window = transform.config.window
    learner_act, evaluation = None, None
    if trained is None:
        act = CONTROLLERS[controller](env)
    else:
        learner_act, evaluation = trained_policy(scenario, trained, train_steps, seed)
        act = None

    def explore(world, key):
        return jax.random.uniform(key, world.position.shape, minval=-1.0, maxval=1.0)

    @jax.jit
    def warm(state, key):
        return run_episode(env, transform, state, None, False, key, controller=explore)[0]

    @jax.jit
    def episode(state, key):
        return run_episode(env, transform, state, learner_act, False, key, controller=act)[1]

    state = transform.init(env, {"lam": 1.0})
    keys = jax.random.split(jax.random.PRNGKey(seed), warmup + 1)
    for key in keys[:-1]:
        state = warm(state, key)
    record = episode(state, keys[-1])
    score = np.asarray(record.info["emergency_score"])  # [T, N, E]: E_{t+1}
    reward = np.abs(np.asarray(record.info["intrinsic_reward"]))  # [T, N, E]
    danger = np.asarray(record.danger) > 0  # [T, N, E]: at t + 1
    position = np.asarray(record.position)[1:]  # [T, N, 2, E]: at t + 1
    offset = position[:, :, None] - position[:, None, :]  # [T, N, N, 2, E]
    distance = np.hypot(offset[:, :, :, 0], offset[:, :, :, 1])
    steps, robots = distance.shape[:2]
    distance[:, np.arange(robots), np.arange(robots)] = np.inf
    contact = distance.min(axis=2) < 2 * env.robot_radius + CONTACT_SLACK  # [T, N, E]
    classes = {"danger": danger, "contact": contact & ~danger, "free": ~contact & ~danger}

    def describe(values: np.ndarray) -> dict[str, float | int]:
        if values.size == 0:
            return {"n": 0}
        q25, q50, q75 = np.quantile(values, [0.25, 0.5, 0.75])
        return {"n": int(values.size), "mean": float(values.mean()), "q25": float(q25),
                "median": float(q50), "q75": float(q75)}

    # Any robot of the environment in danger at t + 1 - k for k = 0..m + 1 (steps t - m..t + 1).
    env_danger = danger.any(axis=1)  # [T, E], index s: state s + 1
    recent = np.zeros_like(env_danger)
    for lag in range(window + 2):
        recent[lag:] |= env_danger[: steps - lag]
    near = np.broadcast_to(recent[:, None, :], reward.shape)
    total = float(reward.sum())
    lead = forewarning(danger, distance, transform.config.comm_range, window)
    return {
        "scenario": scenario,
        "policy": controller if trained is None else f"plain {trained}, {train_steps} steps",
        "trained_evaluation": evaluation,
        "score": {name: describe(score[mask]) for name, mask in classes.items()},
        "share_of_steps": {name: float(mask.mean()) for name, mask in classes.items()},
        "intrinsic_total": total,
        "intrinsic_share_near_danger": float(reward[near].sum() / total) if total > 0 else None,
        "intrinsic_share_in_contact": (float(reward[classes["contact"]].sum() / total)
                                       if total > 0 else None),
        "danger_share_forewarned_by": {
            str(k): (float(forewarned_steps(danger, lead, k).sum() / danger.sum())
                     if danger.any() else None) for k in FOREWARNING_LEADS},
        "forewarning_lead_steps_median": (float(np.median(lead[lead > 0])) if (lead > 0).any()
                                          else None),
        "forewarned_spells": int((lead > 0).sum()),
        "spells": int((danger & ~np.concatenate([np.zeros_like(danger[:1]), danger[:-1]])).sum()),
    }


def forewarning(danger: np.ndarray, distance: np.ndarray, comm_range: float, window: int
                ) -> np.ndarray:
    """How long before each spell of danger its robot had been warned by a teammate.

    ``danger`` ``[T, N, E]`` (bool), ``distance`` ``[T, N, N, E]`` between robots at the
    same steps (``inf`` on the diagonal). A robot is *warned* at step ``t`` if it is not in
    danger itself and a teammate within ``comm_range`` is. A spell of danger (consecutive
    dangerous steps of one robot) starting at ``s`` is *forewarned* if the robot's latest
    streak of warned steps before ``s`` ended at most ``window`` steps before ``s - 1``
    (a warning still fresh); its *lead* is ``s`` minus that streak's first step. Returns
    ``[T, N, E]``: the lead at each forewarned spell's first step, 0 elsewhere.
    """
    teammate = danger[:, None, :, :] & (distance <= comm_range)  # [T, N(i), N(j), E]
    warned = teammate.any(axis=2) & ~danger  # [T, N, E]
    lead = np.zeros(danger.shape, np.int64)
    onset = np.full(danger.shape[1:], -1)  # first step of the current or latest streak
    last_end = np.full(danger.shape[1:], -(10**9))  # last warned step so far
    was_danger = np.zeros(danger.shape[1:], bool)
    was_warned = np.zeros(danger.shape[1:], bool)
    for t in range(danger.shape[0]):
        start = danger[t] & ~was_danger
        fresh = last_end >= t - 1 - window
        lead[t] = np.where(start & fresh, t - onset, 0)  # warnings up to t - 1 only
        onset = np.where(warned[t] & ~was_warned, t, onset)
        last_end = np.where(warned[t], t, last_end)
        was_danger, was_warned = danger[t], warned[t]
    return lead


def forewarned_steps(danger: np.ndarray, lead: np.ndarray, min_lead: int) -> np.ndarray:
    """The dangerous steps ``[T, N, E]`` of the spells whose lead is at least ``min_lead``."""
    steps = np.zeros_like(danger)
    for t in range(danger.shape[0]):
        carried = steps[t - 1] & danger[t] if t else np.zeros_like(danger[0])
        steps[t] = (lead[t] >= min_lead) & (lead[t] > 0) | carried
    return steps


def _g(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def markdown(result: dict[str, Any]) -> str:
    products = ("CCR's model's matrix products take TensorFloat32 operands, as a GPU computes "
                "them by default (emulated). " if result.get("matmul") == "tf32" else "")
    lines = [
        f"{products}Policy `{result['policy']}`, {result['episodes']} episodes per scenario "
        f"after {result['warmup']} episodes of random actions fitting CCR's model; smoothed "
        "emergency score E by the robot's state (median [quartiles], share of robot-steps; "
        "in contact: centres closer than two robot radii plus "
        f"{CONTACT_SLACK:g}, and not in danger), the share of the intrinsic reward's "
        f"magnitude within m = {WINDOW} steps (CCR's rolling-mean window) of a robot of the "
        "same environment being in danger, and the share of dangerous robot-steps that a "
        "teammate's danger forewarned (spells of danger that began while the robot, safe, "
        "had a teammate in danger within communication range, or had had one at most m "
        "steps before; by a lead of at least "
        f"{' / '.join(str(k) for k in FOREWARNING_LEADS)} steps of 0.1 s; median lead): how "
        "much warning this policy leaves to CCR's reflex, not what CCR does.",
        "",
        "| scenario | E in danger | E in contact | E in free motion | "
        "share of |R_in| near danger | share of |R_in| in contact | "
        f"danger forewarned by {' / '.join(str(k) for k in FOREWARNING_LEADS)} steps "
        "(median lead) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        cells = []
        for name in ("danger", "contact", "free"):
            s = row["score"][name]
            share = row["share_of_steps"][name]
            cells.append("none" if s["n"] == 0 else
                         f"{s['median']:.2g} [{s['q25']:.2g}, {s['q75']:.2g}] ({share:.1%})")
        near, contact = row["intrinsic_share_near_danger"], row["intrinsic_share_in_contact"]
        shares = row["danger_share_forewarned_by"]
        lead = row["forewarning_lead_steps_median"]
        lines.append(f"| {row['scenario']} | {' | '.join(cells)} | "
                     f"{'n/a' if near is None else f'{near:.1%}'} | "
                     f"{'n/a' if contact is None else f'{contact:.1%}'} | "
                     + ("no danger" if shares["1"] is None else
                        " / ".join(f"{shares[str(k)]:.1%}" for k in FOREWARNING_LEADS)
                        + f" ({'n/a' if lead is None else f'{lead:g}'})")
                     + " |")
    lines += ["", f"Made by `{result['command']}` at commit `{result['commit']}` in "
              f"{result['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(
        prog=PROG,
        description="Where CCR's emergency score and intrinsic reward arise, under a "
                    "reference controller.",
    )
    parser.add_argument("--controller", default="go_to_goal", choices=sorted(CONTROLLERS),
                        help="reference controller (default go_to_goal)")
    parser.add_argument("--episodes", type=cli.int_in(1, 65536), default=512,
                        help="episodes measured per scenario (default 512)")
    parser.add_argument("--warmup", type=cli.int_in(1, 100_000), default=20,
                        help="episodes that fit CCR's model first (default 20)")
    parser.add_argument("--trained", choices=("iddpg", "maddpg"), default=None,
                        help="measure under this plain learner, trained first in each "
                             "scenario, instead of --controller")
    parser.add_argument("--train-steps", type=cli.positive_int, default=None,
                        help="environment steps of that training, with --trained "
                             f"(default {TRAIN_STEPS:,})")
    parser.add_argument("--seed", type=cli.seed_int, default=0, help="random seed (default 0)")
    parser.add_argument("--matmul", choices=MATMULS, default="float32",
                        help="precision of CCR's model's matrix products: float32, or "
                             "tf32 as a GPU computes them by default (emulated; default "
                             "float32)")
    add_out_options(parser, "ccr_signal/<policy>", Path("runs/ccr_signal"))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.train_steps is not None and args.trained is None:
        cli.fail(PROG, "--train-steps applies only with --trained")
    train_steps = TRAIN_STEPS if args.train_steps is None else args.train_steps
    if args.trained is not None:
        try:  # the budget checked before anything compiles
            TrainConfig(algo=args.trained, scenario="nominal", total_env_steps=train_steps)
        except ValueError as error:
            cli.fail(PROG, str(error))
    prepare_out(PROG, args.out, args.force)
    commit = git_commit()  # the code that measures is the code loaded now
    start = time.time()
    products = tf32_model_products() if args.matmul == "tf32" else contextlib.nullcontext()
    with products:
        rows = [measure(s, args.controller, args.episodes, args.warmup, args.seed, args.trained,
                        train_steps) for s in SCENARIOS]
    result = {
        "policy": rows[0]["policy"], "episodes": args.episodes, "warmup": args.warmup,
        "seed": args.seed, "matmul": args.matmul, "rows": rows, "commit": commit,
        "command": " ".join([PROG, *(argv or sys.argv[1:])]),
        "seconds": time.time() - start,
    }
    text = markdown(result)
    write_atomic(args.out / "ccr_signal.json", json.dumps(result, indent=1))
    write_atomic(args.out / "ccr_signal.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(
        PROG, main,
        "nothing was written (the results are written when the measurement ends)"))
