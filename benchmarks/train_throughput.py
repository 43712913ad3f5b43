"""Speed of the whole training program, per learner, at default settings.

    python benchmarks/train_throughput.py            # table
    python benchmarks/train_throughput.py --json     # one JSON object per line
    python benchmarks/train_throughput.py --algos maddpg --seeds 20   # a grid program's shape
    python benchmarks/train_throughput.py --algos maddpg maac --seeds 3 --maac-updates 4x1024 1x256

For each learner and variant it compiles ``TrainProgram.run`` (rollout of every training
environment through the transform, replay insertion, learner updates, all in one
``lax.scan``), runs ``--iterations`` iterations ``--repeats`` times after compilation, the
variants in turns, with the state donated (as in a long run, no call copies the replay
buffer), and reports the medians: environment steps per second, learner updates per second,
the arithmetic of one update (matrix-multiply FLOPs) with the rate it implies, so the CPU's
utilisation can be judged, and each variant's time per step relative to the first variant's
(with ``--variants plain ccr lagrangian``: CCR's and the Lagrangian's overheads). Learning
starts at once (``learning_starts=0``) so every measured iteration includes its updates.
With ``--seeds N`` the program trains N seeds at once (``vmap``), as the experiments' grid
programs do (20 or 21 runs); the rates are then given per seed and for all seeds together.
With ``--maac-updates GxB ...`` MAAC is timed at each of those update settings (G updates of
batch B every ``update_every`` steps) instead of its default, as ``docs/protocol.md`` chose
the experiments' setting.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import jax
import jax.numpy as jnp

from ccrjax import cli
from ccrjax.agents.maac import MAACConfig
from ccrjax.envs.scenarios import SCENARIOS
from ccrjax.registry import learner_names, transform_names
from ccrjax.run.folder import git_commit
from ccrjax.training import ALGOS, TrainConfig, make_train


def update_setting(text: str) -> tuple[int, int]:
    """``"GxB"`` (updates per round x batch size) as ``(G, B)``, for ``--maac-updates``."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(part.isdigit() and int(part) > 0 for part in parts):
        raise argparse.ArgumentTypeError(
            f"must be updates x batch, two integers > 0 such as 1x256, got {text!r}")
    return int(parts[0]), int(parts[1])


def compiled_run(algo: str, variant: str, scenario: str, iterations: int, seeds: int = 1,
                 learner: MAACConfig | None = None):
    """The compiled ``run`` of ``iterations`` iterations (of ``seeds`` seeds at once when
    more than one), a state to feed it, and the config; ``learner``: the learner's settings
    (``None``: its defaults)."""
    config = TrainConfig(algo=algo, scenario=scenario, variant=variant, learning_starts=0,
                         learner=learner)
    program = make_train(config)

    def one_run(state):
        return program.run(state, iterations)

    if seeds == 1:  # unbatched, as the one-seed rates were always measured
        init, step = program.init, one_run
        key = jax.random.PRNGKey(0)
    else:
        init, step = jax.vmap(program.init), jax.vmap(one_run)
        key = jnp.stack([jax.random.PRNGKey(seed) for seed in range(seeds)])
    # Every leaf its own buffer (the initial targets share their online networks').
    state = jax.tree_util.tree_map(jnp.copy, init(key))
    # The state is donated: a long run carries it from chunk to chunk in place, where an
    # undonated call would first copy the whole replay buffer.
    run = jax.jit(step, donate_argnums=0)
    start = time.perf_counter()
    state, _ = run(state)  # compiles, then fills the buffer a little
    jax.block_until_ready(state)
    return program, config, run, state, time.perf_counter() - start


def update_setting_text(config: TrainConfig) -> str:
    """How a learner updates: ``GxB/S``, G updates of batch B every S environment steps (an
    on-policy learner's: epochs x minibatches over each rollout of S team-steps)."""
    settings = config.resolved_learner
    if config.on_policy:
        return f"{settings.epochs}x{settings.minibatches}mb/{config.steps_per_iteration}"
    return f"{settings.gradient_steps}x{settings.batch_size}/{settings.update_every}"


def update_flops(program) -> float:
    """Matrix-multiply FLOPs of one learner update (an on-policy learner's: the whole
    rollout's, all epochs)."""
    config = program.config
    if config.on_policy:
        return program.learner.flops_per_update(config.num_robots, program.obs_size,
                                                config.steps_per_iteration)
    return program.learner.flops_per_update(config.num_robots, program.obs_size)


def measure(algo: str, variants: list[str], scenario: str, iterations: int, repeats: int,
            seeds: int = 1, learner: MAACConfig | None = None):
    """One row per variant; variants are timed in turns (ABAB...), so that the machine's
    drift affects them alike, and each row gets the median, over rounds, of its time over the
    first variant's in the same round (``time_vs_<first>``, with quartiles: CCR's overhead
    when the first variant is plain)."""
    setups = {v: compiled_run(algo, v, scenario, iterations, seeds, learner)
              for v in variants}
    states = {v: setup[3] for v, setup in setups.items()}
    times: dict[str, list[float]] = {v: [] for v in variants}
    for _ in range(repeats):
        for variant in variants:
            run = setups[variant][2]
            start = time.perf_counter()
            states[variant], _ = run(states[variant])
            jax.block_until_ready(states[variant])
            times[variant].append(time.perf_counter() - start)
    rows = []
    first = variants[0]
    for variant in variants:
        # Paired ratios: each round's time over the first variant's in the same round.
        ratios = sorted(t / b for t, b in zip(times[variant], times[first], strict=True))
        quartiles = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else [ratios[0]] * 3
        program, config, _, _, compile_s = setups[variant]
        median = statistics.median(times[variant])
        updates = iterations * config.updates_per_iteration
        rows.append({
            "algo": algo,
            "variant": variant,
            "updates": update_setting_text(config),
            "num_envs": config.num_envs,
            "scenario": scenario,
            "seeds": seeds,  # trained at once; the rates below are per seed
            "env_steps_per_s": iterations * config.steps_per_iteration / median,
            "env_steps_per_s_all_seeds": seeds * iterations * config.steps_per_iteration
            / median,
            "updates_per_s": updates / median,
            "gflop_per_update": update_flops(program) / 1e9,
            "gflop_per_s": seeds * update_flops(program) * updates / median / 1e9,
            f"time_vs_{first}": statistics.median(ratios),
            f"time_vs_{first}_quartiles": [quartiles[0], quartiles[2]],
            "median_s": median,
            "times_s": times[variant],
            "repeats": repeats,
            "iterations": iterations,
            "first_call_s": compile_s,
            "device": jax.devices()[0].device_kind,
        })
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog="python benchmarks/train_throughput.py",
                        description=__doc__.split("\n")[0])
    parser.add_argument("--algos", nargs="+", choices=learner_names(),
                        default=[*ALGOS, "ippo", "mappo"],
                        help="learners to time (default: the paper's three, IPPO and MAPPO)")
    parser.add_argument("--variants", nargs="+", choices=transform_names(), default=["plain"],
                        help="variants to time, in turns (default: plain); the first is the "
                        "others' reference")
    parser.add_argument("--scenario", choices=tuple(SCENARIOS), default="hidden_obstacle",
                        help="scenario (default: %(default)s)")
    parser.add_argument("--iterations", type=cli.positive_int, default=20,
                        help="training iterations per timed call (default: %(default)s)")
    parser.add_argument("--repeats", type=cli.positive_int, default=5,
                        help="timed calls; the median is reported (default: %(default)s)")
    parser.add_argument("--seeds", type=cli.int_in(1, 1024), default=1,
                        help="seeds trained at once in one vmapped program, as the "
                        "experiments' grids do (default: %(default)s)")
    parser.add_argument("--maac-updates", nargs="+", type=update_setting,
                        metavar="GxB", default=None,
                        help="time MAAC at each of these update settings, G updates of "
                        "batch B per round (default: its defaults, 4x1024)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per line instead of a table")
    args = parser.parse_args(argv)

    rows = []
    learners: dict[str, list[MAACConfig | None]] = {algo: [None] for algo in args.algos}
    if args.maac_updates and "maac" in learners:
        learners["maac"] = [MAACConfig(gradient_steps=g, batch_size=b)
                            for g, b in args.maac_updates]
    for algo in args.algos:
        for learner in learners[algo]:
            for row in measure(algo, args.variants, args.scenario, args.iterations,
                               args.repeats, args.seeds, learner):
                rows.append(row)
                if args.json:
                    print(json.dumps(row), flush=True)
    if not args.json:
        print(f"{platform.node()} · {jax.devices()[0].device_kind} · jax {jax.__version__} · "
              f"commit {git_commit()[:12]}")
        seeds = ("one seed" if args.seeds == 1 else
                 f"{args.seeds} seeds in one vmapped program (env steps/s and updates/s per "
                 "seed; 'all seeds': together; GFLOP/s: all seeds)")
        settings = ("default learner settings, MAAC's as --maac-updates names"
                    if args.maac_updates else "default learner settings")
        print(f"{seeds}, {args.scenario}, {settings}, learning from the first "
              "step (the rate of a run after its warm-up)")
        first = args.variants[0]
        together = f" {'all seeds':>12}" if args.seeds > 1 else ""
        header = (
            f"{'learner':8} {'variant':12} {'updates':>11} {'env steps/s':>12}{together} "
            f"{'updates/s':>10} "
            f"{'GFLOP/upd':>10} {'GFLOP/s':>8} {'time vs ' + first:>14} {'quartiles':>13}"
        )
        print(header)
        print("-" * len(header))
        for row in rows:
            all_seeds = (f" {row['env_steps_per_s_all_seeds']:12,.0f}" if args.seeds > 1
                         else "")
            print(
                f"{row['algo']:8} {row['variant']:12} {row['updates']:>11} "
                f"{row['env_steps_per_s']:12,.0f}{all_seeds} "
                f"{row['updates_per_s']:10.1f} {row['gflop_per_update']:10.2f} "
                f"{row['gflop_per_s']:8.1f} {row['time_vs_' + first]:14.3f} "
                f"{row['time_vs_' + first + '_quartiles'][0]:6.3f}-"
                f"{row['time_vs_' + first + '_quartiles'][1]:.3f}"
            )
        print("'updates': updates per round x batch / environment steps between rounds; "
              "on-policy: epochs x minibatches / team-steps per rollout (one update)")
        print(f"median of {args.repeats} runs of {args.iterations} iterations after compilation, "
              f"variants timed in turns; 'time vs {first}': median (and quartiles) of each "
              "round's time over the first variant's in the same round")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
