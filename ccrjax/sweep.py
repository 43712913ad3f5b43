"""Grids of training runs in one program, and ``python -m ccrjax.sweep``, the lambda search.

:func:`train_grid` trains every entry of a grid (a seed, and per-run transform
numbers such as CCR's lambda or the pessimistic penalty) of one configuration as
one vmapped program, sharded over every device (:mod:`ccrjax.grid`). It returns
each run's evaluation history and its final policy (learner and transform
state; the replay buffers stay inside the program). The experiments build on it:
``experiments/tables.py``, ``experiments/behaviour.py``, and this module's command::

    python -m ccrjax.sweep --scenario hidden_obstacle --algo maddpg \\
        --lams 0 1 3 10 30 100 --seeds 5 --out runs/sweep

which trains ``len(lams) x seeds`` CCR runs at once and writes ``sweep.md`` (a table
of the four metrics per lambda, mean and 95% interval over seeds), ``sweep.json``
(per-seed values) and ``tradeoff.png`` (dangerous-behaviour frequency against
success rate, one point per lambda with its intervals).
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
from ccrjax.rollout import run_episode
from ccrjax.run_folder import POINT_METRICS, git_commit, write_atomic
from ccrjax.stats import mean_ci
from ccrjax.training import TrainConfig, make_env, make_train

PROG = "python -m ccrjax.sweep"
DEFAULT_LAMS = (0.0, 1.0, 3.0, 10.0, 30.0, 100.0)


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
            from ccrjax.training import NonFiniteTraining

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


def summarise(values: np.ndarray) -> dict[str, Any]:
    """Per-seed values with their mean and 95% interval."""
    return {"per_seed": [float(v) for v in values], **mean_ci(values)}


# ---------------------------------------------------------------------------- the command
def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="Search CCR's lambda: every lambda x seed "
                        "trained at once, then a table and the safety-efficiency trade-off.")
    parser.add_argument("--scenario", choices=("turbulence", "strong_wind", "hidden_obstacle",
                                               "nominal"), default="hidden_obstacle",
                        help="scenario (default: %(default)s)")
    parser.add_argument("--algo", choices=("iddpg", "maddpg", "maac"), default="maddpg",
                        help="learner (default: %(default)s)")
    parser.add_argument("--lams", type=cli.non_negative_float, nargs="+",
                        default=list(DEFAULT_LAMS),
                        help="lambda values (default: 0 1 3 10 30 100)")
    parser.add_argument("--seeds", type=cli.int_in(1, 1024), default=5,
                        help="seeds per lambda (default: %(default)s)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=0,
                        help="first seed (default: %(default)s)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: the learner's default budget)")
    parser.add_argument("--eval-episodes", type=cli.int_in(1, 65536), default=128,
                        help="episodes per evaluation (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"),
                        help="output folder (default: %(default)s)")
    return parser


def run_sweep(args: argparse.Namespace) -> dict[str, Any]:
    config = TrainConfig(algo=args.algo, scenario=args.scenario, variant="ccr",
                         total_env_steps=args.steps, eval_episodes=args.eval_episodes)
    config = dataclasses.replace(config, eval_every=config.total_env_steps // 10 or 1)
    lams = [float(v) for v in args.lams]
    seeds = [args.seed_offset + k for k in range(args.seeds)]
    grid_seeds = [s for _ in lams for s in seeds]
    grid_lams = [lam for lam in lams for _ in seeds]
    print(f"{PROG}: {args.algo} + CCR on {args.scenario}: {len(lams)} lambda x {len(seeds)} "
          f"seeds = {len(grid_seeds)} runs of {config.total_env_steps:,} steps, one program",
          file=sys.stderr, flush=True)
    runs = train_grid(config, grid_seeds, {"lam": grid_lams},
                      log=lambda text: print(text, file=sys.stderr, flush=True))
    final = runs.final
    rows = []
    for lam in lams:
        mask = np.asarray(grid_lams) == lam
        rows.append({"lam": lam, "seeds": seeds,
                     **{m: summarise(final[m][mask]) for m in POINT_METRICS}})
    result = {
        "scenario": args.scenario, "algo": args.algo, "env_steps": config.total_env_steps,
        "eval_episodes": args.eval_episodes, "compile_s": runs.compile_s, "run_s": runs.run_s,
        "devices": [f"{d.platform}:{d.device_kind}" for d in jax.devices()],
        "command": " ".join([PROG, *sys.argv[1:]]), "commit": git_commit(), "rows": rows,
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
    lines = [
        f"# Lambda sweep: {result['algo']} + CCR on {result['scenario']}",
        "",
        f"{result['env_steps']:,} environment steps per run, {len(result['rows'][0]['seeds'])} "
        f"seeds per lambda, {result['eval_episodes']} evaluation episodes; mean ± 95% CI "
        "(Student t) over seeds. Command: `" + result["command"] + "`.",
        "",
        "| lambda | danger frequency | success rate | return | distance to hazard |",
        "|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        lines.append(
            f"| {row['lam']:g} | {_cell(row['danger_frequency'], True)} | "
            f"{_cell(row['success_rate'], True)} | {_cell(row['return'], False)} | "
            f"{_cell(row['hazard_distance'], False)} |"
        )
    return "\n".join(lines) + "\n"


def draw_tradeoff(result: dict[str, Any], path: Path) -> None:
    """Danger frequency against success rate, one point per lambda with 95% intervals."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.6, 4.4), dpi=130)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for row in result["rows"]:
        success, danger = row["success_rate"], row["danger_frequency"]
        ax.errorbar(success["mean"], danger["mean"],
                    xerr=success["half_width"] or 0.0, yerr=danger["half_width"] or 0.0,
                    marker="o", capsize=3, linewidth=1)
        ax.annotate(f"λ={row['lam']:g}", (success["mean"], danger["mean"]),
                    textcoords="offset points", xytext=(6, 6), fontsize=8)
    ax.set_xlabel("success rate (higher is better)")
    ax.set_ylabel("dangerous-behaviour frequency (lower is better)")
    ax.set_title(f"{result['algo']} + CCR, {result['scenario']}: safety vs efficiency",
                 fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    temporary = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(temporary)
    temporary.replace(path)


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
