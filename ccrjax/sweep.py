"""Grids of training runs in one program, and ``python -m ccrjax.sweep``, a search of one pair.

:func:`train_grid` trains every entry of a grid (a seed, and per-run transform
numbers such as CCR's lambda or the pessimistic penalty) of one configuration as
one vmapped program, sharded over every device (:mod:`ccrjax.grid`). It returns
each run's evaluation history and its final policy (learner and transform
state; the replay buffers stay inside the program). The experiments build on it:
``experiments/search.py`` (the searches of every scenario and learner, ``make sweep``
and ``make penalty-sweep``), ``experiments/tables.py``, ``experiments/behaviour.py``,
and this module's command, one scenario and learner::

    python -m ccrjax.sweep --variant ccr --scenario hidden_obstacle --algo maddpg \\
        --values 0 1 3 10 30 100 --seeds 3 --out runs/sweep
    python -m ccrjax.sweep --variant pessimistic --values 0 0.1 1 10 --out runs/penalty

which trains ``len(values) x seeds`` runs at once (0 is the plain learner: CCR's
reward unchanged, or no penalty) and writes ``sweep.md`` (a table of the metrics per
value, mean and 95% interval over seeds), ``sweep.json`` (per-seed values) and
``tradeoff.png`` (dangerous-behaviour frequency against success rate, one point per
value with its intervals).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ccrjax import cli
from ccrjax.cli import UsageError
from ccrjax.grid import GridProgram, stack_keys
from ccrjax.plots import draw_search_tradeoff
from ccrjax.rollout import run_episode
from ccrjax.run_folder import METRIC_RANGES, POINT_METRICS, git_commit, write_atomic
from ccrjax.stats import mean_ci
from ccrjax.training import (
    ALGOS,
    LEARNING_STARTS,
    NonFiniteTraining,
    TrainConfig,
    make_env,
    make_train,
)

PROG = "python -m ccrjax.sweep"
# The run parameter each searchable variant takes, and the values searched by default
# (the protocol's, docs/protocol.md).
SEARCHED_PARAMETER = {"ccr": "lam", "pessimistic": "penalty"}
DEFAULT_VALUES = {"ccr": (0.3, 1.0, 3.0, 10.0, 30.0, 100.0),
                  "pessimistic": (0.03, 0.1, 0.3, 1.0, 3.0, 10.0)}
SCENARIO_NAMES = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")


@dataclasses.dataclass
class GridRuns:
    """The results of :func:`train_grid`: entry ``g`` is ``seeds[g]`` with ``params[...][g]``."""

    config: TrainConfig
    seeds: list[int]
    params: dict[str, np.ndarray]  # [G] per transform parameter
    history: dict[str, np.ndarray]  # [G, evaluations + 1] per metric (and env_steps)
    policy: Any  # (learner state, transform state), leaves [G, ...]
    episodes: dict[str, np.ndarray] | None  # recorded evaluation episodes, leaves [G, ...]
    compile_s: float
    run_s: float

    @property
    def final(self) -> dict[str, np.ndarray]:
        """The last evaluation of every run, ``[G]`` per metric."""
        return {name: values[:, -1] for name, values in self.history.items()}

    def select(self, mask: np.ndarray) -> GridRuns:
        """The runs where ``mask`` ``[G]`` holds."""
        index = np.flatnonzero(mask)
        return dataclasses.replace(
            self,
            seeds=[self.seeds[i] for i in index],
            params={k: v[index] for k, v in self.params.items()},
            history={k: v[index] for k, v in self.history.items()},
            policy=jax.tree_util.tree_map(lambda x: x[index], self.policy),
            episodes=None if self.episodes is None
            else {k: v[index] for k, v in self.episodes.items()},
        )


class GridTraining:
    """A grid of runs of one configuration, compiled and run as one sharded program.

    Entry ``g`` trains with seed ``seeds[g]`` and the transform numbers ``params[name][g]``
    (e.g. ``{"lam": [...]}``, ``{"penalty": [...]}``); the others take the configuration's
    values. With ``record_episodes > 0`` the same program then runs that many fresh
    evaluation episodes of every trained team (deterministic policies; the same starts
    and hazards for every entry, drawn from ``record_key``) and returns what happened in
    them (:attr:`GridRuns.episodes`). :meth:`compile` and :meth:`run` are separate so
    that a caller can compile the next grid while this one trains.
    """

    def __init__(
        self,
        config: TrainConfig,
        seeds: Sequence[int],
        params: dict[str, Sequence[float]] | None = None,
        *,
        record_episodes: int = 0,
        record_key: jax.Array | None = None,
    ) -> None:
        self.config = config
        self.seeds = [int(s) for s in seeds]
        program = make_train(config)
        defaults = program.default_transform_params()
        given = {k: np.asarray(v, np.float32) for k, v in (params or {}).items()}
        for name, values in given.items():
            if name not in defaults:
                raise ValueError(f"variant {config.variant!r} takes the run parameters "
                                 f"{sorted(defaults)}, not {name!r}")
            if values.shape != (len(self.seeds),):
                raise ValueError(f"params[{name!r}] must hold one value per seed "
                                 f"({len(self.seeds)})")
        self.params = {name: given.get(name, np.full(len(self.seeds), value, np.float32))
                       for name, value in defaults.items()}
        self.inputs = {"key": np.asarray(stack_keys(self.seeds)), "params": self.params}
        record_env = make_env(config, record_episodes) if record_episodes else None
        record_key = jax.random.PRNGKey(0) if record_key is None else record_key

        def one_run(entry: dict[str, Any]):
            state, history = program.train(entry["key"], entry["params"])
            out = {"policy": (state.learner, state.transform), "history": history,
                   "nonfinite": state.nonfinite_iteration}
            if record_env is not None:
                def greedy(obs, step_key):
                    return program.learner.act(state.learner, obs, step_key, False)

                _, episode = run_episode(record_env, program.transform, state.transform,
                                         greedy, program.learner.discrete, record_key)
                out["episodes"] = {
                    "position": episode.position,
                    "danger": episode.danger,
                    "success": episode.success[-1],  # [N, E]: in the target area at the end
                    "hazard_centre": episode.hazard.centre,
                    "hazard_half_extent": episode.hazard.half_extent,
                    **episode.info,
                }
            return out

        self.grid = GridProgram(one_run)
        self.compile_s = 0.0

    def compile(self, optimize: bool = True) -> float:
        """Compiles the program (thread-safe to call from a worker); returns the seconds.
        ``optimize=False``: see :meth:`ccrjax.grid.GridProgram.compile`."""
        start = time.perf_counter()
        self.grid.compile(self.inputs, optimize)
        self.compile_s = time.perf_counter() - start
        return self.compile_s

    def run(self) -> GridRuns:
        """Trains every entry; raises :class:`ccrjax.training.NonFiniteTraining` if one went
        non-finite."""
        start = time.perf_counter()
        out = self.grid(self.inputs)
        run_s = time.perf_counter() - start
        nonfinite = out["nonfinite"]
        if np.any(nonfinite >= 0):
            bad = int(np.flatnonzero(nonfinite >= 0)[0])
            raise NonFiniteTraining(f"run {bad} (seed {self.seeds[bad]}) became non-finite at "
                                    f"iteration {int(nonfinite[bad])}")
        return GridRuns(config=self.config, seeds=self.seeds, params=self.params,
                        history={k: np.asarray(v) for k, v in out["history"].items()},
                        policy=out["policy"], episodes=out.get("episodes"),
                        compile_s=self.compile_s, run_s=run_s)


def train_grid(
    config: TrainConfig,
    seeds: Sequence[int],
    params: dict[str, Sequence[float]] | None = None,
    *,
    record_episodes: int = 0,
    record_key: jax.Array | None = None,
    log=None,
) -> GridRuns:
    """Compiles and runs a :class:`GridTraining` (see there)."""
    training = GridTraining(config, seeds, params, record_episodes=record_episodes,
                            record_key=record_key)
    compile_s = training.compile()
    if log:
        log(f"  compiled in {compile_s:.1f} s ({training.grid.num_devices} device(s)); "
            f"training {len(training.seeds)} run(s) ...")
    return training.run()


def summarise(values: np.ndarray, metric: str) -> dict[str, Any]:
    """Per-seed values of ``metric`` with their mean and 95% interval (within its range)."""
    return {"per_seed": [float(v) for v in values],
            **mean_ci(values, bounds=METRIC_RANGES[metric])}


def search_grid(config: TrainConfig, values: Sequence[float], seeds: Sequence[int]
                ) -> tuple[str, list[int], list[float]]:
    """The grid of a search of ``config.variant``'s run parameter (CCR's ``lam``, the
    pessimistic ``penalty``): every value with every seed, values outer."""
    name = SEARCHED_PARAMETER.get(config.variant)
    if name is None:
        raise ValueError(f"variant must be one of {sorted(SEARCHED_PARAMETER)} to search, "
                         f"got {config.variant!r}")
    grid_seeds = [int(s) for _ in values for s in seeds]
    grid_values = [float(v) for v in values for _ in seeds]
    return name, grid_seeds, grid_values


def search_rows(runs: GridRuns, values: Sequence[float], grid_values: Sequence[float],
                seeds: Sequence[int]) -> list[dict[str, Any]]:
    """One row per value: the per-seed final metrics with their means and intervals."""
    final = runs.final
    rows = []
    for value in values:
        mask = np.asarray(grid_values) == float(value)
        rows.append({"value": float(value), "seeds": list(seeds),
                     **{m: summarise(final[m][mask], m) for m in POINT_METRICS}})
    return rows


# ---------------------------------------------------------------------------- the command
def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="Search the pessimistic penalty or CCR's lambda "
                        "for one scenario and learner: every value x seed trained at once, then "
                        "a table and the safety-efficiency trade-off.")
    parser.add_argument("--variant", choices=sorted(SEARCHED_PARAMETER), default="ccr",
                        help="what to search: ccr (lambda) or pessimistic (penalty) "
                        "(default: %(default)s)")
    parser.add_argument("--scenario", choices=SCENARIO_NAMES, default="hidden_obstacle",
                        help="scenario (default: %(default)s)")
    parser.add_argument("--algo", choices=ALGOS, default="maddpg",
                        help="learner (default: %(default)s)")
    parser.add_argument("--values", type=cli.non_negative_float, nargs="+", default=None,
                        help="values of lambda or of the penalty; 0 is the plain learner "
                        "(default: 0 and the protocol's six values, docs/protocol.md)")
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=3,
                        help="seeds per value, at least 2 for an interval (default: %(default)s)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=100,
                        help="first seed (default: %(default)s, the selection seeds: disjoint "
                        "from the tables' 0-9)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: the learner's default budget)")
    parser.add_argument("--learning-starts", type=cli.int_in(0), default=LEARNING_STARTS,
                        help="transitions per seed before the first update "
                        "(default: %(default)s)")
    parser.add_argument("--eval-episodes", type=cli.int_in(1, 65536), default=128,
                        help="episodes per evaluation (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"),
                        help="output folder (default: %(default)s)")
    return parser


def run_sweep(args: argparse.Namespace) -> dict[str, Any]:
    config = TrainConfig(algo=args.algo, scenario=args.scenario, variant=args.variant,
                         total_env_steps=args.steps, eval_episodes=args.eval_episodes,
                         learning_starts=args.learning_starts)
    config = dataclasses.replace(config, eval_every=config.total_env_steps // 10 or 1)
    values = [0.0, *DEFAULT_VALUES[args.variant]] if args.values is None else args.values
    values = sorted({float(v) for v in values})
    seeds = [args.seed_offset + k for k in range(args.seeds)]
    name, grid_seeds, grid_values = search_grid(config, values, seeds)
    print(f"{PROG}: {args.algo} + {args.variant} on {args.scenario}: {len(values)} {name} x "
          f"{len(seeds)} seeds = {len(grid_seeds)} runs of {config.total_env_steps:,} steps, "
          "one program", file=sys.stderr, flush=True)
    runs = train_grid(config, grid_seeds, {name: grid_values},
                      log=lambda text: print(text, file=sys.stderr, flush=True))
    result = {
        "variant": args.variant, "parameter": name,
        "scenario": args.scenario, "algo": args.algo, "env_steps": config.total_env_steps,
        "eval_episodes": args.eval_episodes, "compile_s": runs.compile_s, "run_s": runs.run_s,
        "devices": [f"{d.platform}:{d.device_kind}" for d in jax.devices()],
        "command": " ".join([PROG, *sys.argv[1:]]), "commit": git_commit(),
        "rows": search_rows(runs, values, grid_values, seeds),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out / "sweep.json", json.dumps(result, indent=2) + "\n")
    write_atomic(args.out / "sweep.md", sweep_table(result))
    draw_tradeoff(result, args.out / "tradeoff.png")
    return result


def _cell(stats: dict[str, Any], percent: bool) -> str:
    scale, unit = (100.0, "%") if percent else (1.0, "")
    text = f"{stats['mean'] * scale:.2f}{unit}"
    if stats.get("half_width") is not None:
        text += f" ± {stats['half_width'] * scale:.2f}"
    return text


def sweep_table(result: dict[str, Any]) -> str:
    name = result["parameter"]
    lines = [
        f"# Search of {name}: {result['algo']} + {result['variant']} on {result['scenario']}",
        "",
        f"{result['env_steps']:,} environment steps per run, {len(result['rows'][0]['seeds'])} "
        f"seeds per value, {result['eval_episodes']} evaluation episodes; mean ± half-width "
        "of the 95% CI (Student t) over seeds; 0 is the plain learner. Command: `"
        + result["command"] + "`.",
        "",
        f"| {name} | danger frequency | success rate | return | distance to hazard |",
        "|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        lines.append(
            f"| {row['value']:g} | {_cell(row['danger_frequency'], True)} | "
            f"{_cell(row['success_rate'], True)} | {_cell(row['return'], False)} | "
            f"{_cell(row['hazard_distance'], False)} |"
        )
    return "\n".join(lines) + "\n"


def draw_tradeoff(result: dict[str, Any], path: Path) -> None:
    """Danger frequency against success rate, one point per value with 95% intervals."""
    title = f"{result['algo']} + {result['variant']}, {result['scenario']}: safety vs efficiency"
    draw_search_tradeoff({title: result["rows"]}, result["parameter"], path)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cli.enable_compilation_cache(cli.default_cache_dir())
    try:
        result = run_sweep(args)
    except (UsageError, ValueError) as error:
        cli.fail(PROG, str(error))
    print(sweep_table(result))
    print(f"wrote {args.out / 'sweep.md'}, {args.out / 'sweep.json'}, "
          f"{args.out / 'tradeoff.png'} (training {result['run_s']:.0f} s, compiling "
          f"{result['compile_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
