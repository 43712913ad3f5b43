"""The paper's Tables I and II, with seeds and confidence intervals: ``make tables``.

    python experiments/tables.py                       # the full grid, 5 seeds (42-50 min)
    python experiments/tables.py --seeds 10 --seed-offset 100   # fresh seeds, more of them
    python experiments/tables.py --quick --out /tmp/q  # a tiny budget, for the tests

Trains the grid 3 scenarios x 3 learners x 3 variants (plain, pessimistic, CCR at
lambda 30), ``--seeds`` seeds each. Per scenario and learner, two programs: plain and
pessimistic together (one program; plain is the pessimistic transform with penalty 0,
exactly), and CCR; each trains all its runs at once, sharded over every device
(:mod:`ccrjax.grid`). While one program trains, the next one compiles.

Every finished cell (scenario, learner, variant) is written atomically to
``<out>/cells/<scenario>-<algo>-<variant>.json`` with its per-seed results, curves and
behaviour measurements; a re-run skips the cells already there (if they were made with
the same settings), so a killed run loses only the cells in progress. Every run of the
script is recorded in ``<out>/invocations.json`` (command, commit, date, wall time, programs
trained, whether it finished), rewritten after each program, so a run that is killed keeps
its record. Then it writes:

* ``<out>/tables.md``: Table I (dangerous-behaviour frequency) and Table II (success
  rate) in the paper's layout, each cell our mean and 95% interval over seeds beside the
  paper's number; the same for the average distance to the hazard centre and the
  return; the paper's headline figures recomputed from our runs (with bootstrap 95%
  intervals over seeds); and the direction of the paper's claims, cell by cell;
* ``<out>/tables.json``: one record per scenario, learner and variant with the
  per-seed values and the mean and interval of every metric;
* figures: ``curves_hidden_obstacle_maddpg.png`` (training curves of MADDPG and
  MADDPG+CCR with 95% bands), ``trajectories_hidden_obstacle_maddpg.png`` (the same
  episode by both teams, CCR's colours), ``distance_hidden_obstacle_maddpg.png`` (the
  average distance to the obstacle per robot, in order of arrival).

The budget (``--steps``, default 150,000 environment steps per run for every learner,
and MAAC with one update of batch 256 every 100 steps instead of the original's four of
1024) is what fits the whole grid in an hour on a 2-core CPU; the README says what that
costs in fidelity.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ccrjax import cli
from ccrjax.analysis import arrival_analysis
from ccrjax.learners.ddpg import DDPGConfig
from ccrjax.learners.maac import MAACConfig
from ccrjax.paper import PAPER, PAPER_HEADLINES, SCENARIOS
from ccrjax.run_folder import POINT_METRICS, git_commit, write_atomic
from ccrjax.stats import mean_ci
from ccrjax.sweep import GridRuns, GridTraining
from ccrjax.training import TrainConfig

ALGOS = ("iddpg", "maddpg", "maac")
VARIANTS = ("plain", "pessimistic", "ccr")
LEARNER_NAMES = {"iddpg": "DDPG", "maddpg": "MADDPG", "maac": "MAAC"}
VARIANT_SUFFIX = {"plain": "", "pessimistic": " (Pessimistic)", "ccr": "+CCR"}
SCENARIO_NAMES = {"hidden_obstacle": "hidden obstacle", "turbulence": "turbulence",
                  "strong_wind": "strong wind"}
METRICS = POINT_METRICS

# The paper's Tables I and II (percent), by (scenario, learner, variant).
RESULTS = Path(__file__).resolve().parent / "results"


@dataclasses.dataclass(frozen=True)
class Settings:
    """What every cell is trained with (a cell made with other settings is redone)."""

    steps: int = 150_000
    seeds: int = 5
    seed_offset: int = 0
    eval_every: int = 15_000
    eval_episodes: int = 64
    lam: float = 30.0
    penalty: float = 1.0
    maac_gradient_steps: int = 1
    maac_batch_size: int = 256
    behaviour_episodes: int = 64
    quick: bool = False

    def config(self, scenario: str, algo: str, variant: str) -> TrainConfig:
        base = TrainConfig(algo=algo, scenario=scenario, variant=variant,
                           total_env_steps=self.steps, eval_every=self.eval_every,
                           eval_episodes=self.eval_episodes, penalty=self.penalty)
        changes: dict[str, Any] = {"ccr": dataclasses.replace(base.ccr, lam=self.lam)}
        if algo == "maac":
            changes["maac"] = dataclasses.replace(
                base.maac, gradient_steps=self.maac_gradient_steps,
                batch_size=self.maac_batch_size)
        if self.quick:  # tiny networks and batches: the pipeline, not the learning
            changes.update(num_envs=2, episode_length=10, learning_starts=40)
            changes["ddpg"] = DDPGConfig(batch_size=32, actor_hidden=(8,), critic_hidden=(8,),
                                         update_every=20)
            changes["maac"] = MAACConfig(batch_size=32, policy_hidden=(8,), critic_hidden=8,
                                         attention_heads=2, update_every=20, gradient_steps=1)
        return dataclasses.replace(base, **changes)

    @property
    def seed_list(self) -> list[int]:
        return list(range(self.seed_offset, self.seed_offset + self.seeds))


QUICK = dict(steps=400, seeds=2, eval_every=200, eval_episodes=4, behaviour_episodes=4)


@dataclasses.dataclass
class Job:
    """One program: a scenario and learner, one or two variants, all their seeds."""

    scenario: str
    algo: str
    variants: tuple[str, ...]
    training: GridTraining | None = None

    @property
    def name(self) -> str:
        return f"{self.scenario}-{self.algo}-{'+'.join(self.variants)}"


def cell_path(out: Path, scenario: str, algo: str, variant: str) -> Path:
    return out / "cells" / f"{scenario}-{algo}-{variant}.json"


def read_cell(path: Path, settings: Settings) -> dict | None:
    """A finished cell made with ``settings``, or None."""
    try:
        cell = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return cell if cell.get("settings") == dataclasses.asdict(settings) else None


def build_training(job: Job, settings: Settings) -> GridTraining:
    seeds = settings.seed_list
    key = jax.random.PRNGKey(2**30 + 11)  # episodes no training evaluation has seen
    episodes = settings.behaviour_episodes
    if job.variants == ("plain", "pessimistic"):
        config = settings.config(job.scenario, job.algo, "pessimistic")
        penalties = [0.0] * len(seeds) + [settings.penalty] * len(seeds)
        return GridTraining(config, seeds + seeds, {"penalty": penalties},
                            record_episodes=episodes, record_key=key)
    config = settings.config(job.scenario, job.algo, "ccr")
    return GridTraining(config, seeds, {"lam": [settings.lam] * len(seeds)},
                        record_episodes=episodes, record_key=key)


def cells_of(job: Job, runs: GridRuns, settings: Settings) -> dict[str, dict]:
    """The finished cells of a job's runs, by variant."""
    seeds = settings.seed_list
    cells = {}
    for index, variant in enumerate(job.variants):
        part = runs.select(np.arange(len(runs.seeds)) // len(seeds) == index)
        final = part.final
        cell = {
            "scenario": job.scenario, "algo": job.algo, "variant": variant,
            "settings": dataclasses.asdict(settings), "seeds": part.seeds,
            "params": {k: [float(x) for x in v] for k, v in part.params.items()},
            "final": {m: [float(x) for x in final[m]] for m in METRICS},
            "history": {m: part.history[m].tolist() for m in (*METRICS, "env_steps")},
            "train_seconds_of_program": runs.run_s,
            "compile_seconds_of_program": runs.compile_s,
        }
        episodes = part.episodes
        if job.scenario == "hidden_obstacle":
            analysis = arrival_analysis(episodes, reach=0.3)
            cell["arrival"] = {  # per seed and arrival rank, means over episodes
                "closest": analysis["closest"].mean(axis=1).tolist(),
                "centre_distance": analysis["centre_distance"].mean(axis=1).tolist(),
            }
        cell["episode"] = {  # the first recorded episode of the first seed, for pictures
            "position": episodes["position"][0, ..., 0].tolist(),
            "hazard_centre": episodes["hazard_centre"][0, :, 0].tolist(),
            "hazard_half_extent": episodes["hazard_half_extent"][0, :, 0].tolist(),
            "ccr_state": (episodes["ccr_state"][0, ..., 0].tolist()
                          if "ccr_state" in episodes else None),
        }
        cells[variant] = cell
    return cells


def run_grid(settings: Settings, out: Path, log,
             on_program_done: Callable[[int], None] = lambda trained: None
             ) -> tuple[dict, int]:
    """Trains every missing cell (compiling the next program while one trains); returns
    the cells by (scenario, algo, variant) and the number of programs trained.
    ``on_program_done(trained)`` is called once a program's cells are written."""
    jobs = []
    for scenario in SCENARIOS:
        for algo in ALGOS:
            for variants in (("plain", "pessimistic"), ("ccr",)):
                jobs.append(Job(scenario, algo, variants))
    cells: dict[tuple[str, str, str], dict] = {}
    todo = []
    for job in jobs:
        found = [read_cell(cell_path(out, job.scenario, job.algo, v), settings)
                 for v in job.variants]
        if all(found):
            for variant, cell in zip(job.variants, found, strict=True):
                cells[(job.scenario, job.algo, variant)] = cell
        else:
            todo.append(job)
    log(f"{len(jobs) - len(todo)} of {len(jobs)} programs already done; {len(todo)} to train "
        f"({settings.seeds} seeds, {settings.steps:,} steps per run, "
        f"{jax.device_count()} device(s))")
    (out / "cells").mkdir(parents=True, exist_ok=True)
    # Compilation runs ahead in worker threads (XLA's compiler releases the GIL) while the
    # main thread trains; the quick mode's programs run for moments, so there it compiles
    # on both cores at XLA's lowest optimisation level.
    workers = 2 if settings.quick else 1
    with ThreadPoolExecutor(max_workers=workers) as compiler:
        for job in todo:
            job.training = build_training(job, settings)
        compiled = [compiler.submit(job.training.compile, not settings.quick) for job in todo]
        for number, (job, done) in enumerate(zip(todo, compiled, strict=True), start=1):
            done.result()
            runs = job.training.run()
            for variant, cell in cells_of(job, runs, settings).items():
                write_atomic(cell_path(out, job.scenario, job.algo, variant),
                             json.dumps(cell) + "\n")
                cells[(job.scenario, job.algo, variant)] = cell
            log(f"[{number}/{len(todo)}] {job.name}: trained {len(runs.seeds)} runs in "
                f"{runs.run_s:.0f} s (compiled in {runs.compile_s:.0f} s)")
            job.training = None  # free the compiled program
            on_program_done(number)
    return cells, len(todo)


# ---------------------------------------------------------------------------- the numbers
def stats(values: list[float]) -> dict[str, Any]:
    return {"per_seed": values, **mean_ci(values)}


def relative_change(new: np.ndarray, base: np.ndarray) -> float:
    """``(mean(new) - mean(base)) / mean(base)``; NaN where the base is 0."""
    base_mean = float(np.mean(base))
    return float((np.mean(new) - base_mean) / base_mean) if base_mean != 0 else float("nan")


def headline(cells, metric: str, new: str, base: str, sign: float,
             resamples: int = 2000, seed: int = 0) -> dict[str, Any]:
    """The paper's averaged relative change over the 9 scenario x learner pairs.

    ``sign = -1``: reduction ``(base - new) / base``; ``+1``: increase. Pairs whose base
    mean is 0 are left out (and counted). The interval resamples seeds within every cell
    (bootstrap, ``resamples`` times) and takes the 2.5 and 97.5 percentiles.
    """
    rng = np.random.default_rng(seed)
    pairs = [(s, a) for s in SCENARIOS for a in ALGOS]
    values, used = [], []
    for scenario, algo in pairs:
        n = np.asarray(cells[(scenario, algo, new)]["final"][metric])
        b = np.asarray(cells[(scenario, algo, base)]["final"][metric])
        change = relative_change(n, b)
        if np.isfinite(change):
            values.append(sign * change)
            used.append((scenario, algo, n, b))
    if not used:
        return {"mean": None, "ci_low": None, "ci_high": None, "pairs": 0}
    boot = np.empty(resamples)
    for r in range(resamples):
        total = 0.0
        for _, _, n, b in used:
            nb = rng.choice(n, n.size)
            bb = rng.choice(b, b.size)
            bm = bb.mean()
            total += sign * (nb.mean() - bm) / bm if bm != 0 else 0.0
        boot[r] = total / len(used)
    return {"mean": float(np.mean(values)), "ci_low": float(np.percentile(boot, 2.5)),
            "ci_high": float(np.percentile(boot, 97.5)), "pairs": len(used),
            "left_out": len(pairs) - len(used)}


def welch_significant(a: list[float], b: list[float]) -> bool:
    """Whether the 95% Welch interval of ``mean(a) - mean(b)`` excludes 0."""
    from scipy import stats as scipy_stats

    a, b = np.asarray(a), np.asarray(b)
    if a.size < 2 or b.size < 2:
        return False
    if np.std(a) == 0 and np.std(b) == 0:
        return bool(np.mean(a) != np.mean(b))
    return bool(scipy_stats.ttest_ind(a, b, equal_var=False).pvalue < 0.05)


def claims(cells) -> dict[str, Any]:
    """The direction of the paper's main claims, checked cell by cell."""
    result: dict[str, Any] = {}
    for base in ("plain", "pessimistic"):
        lower, significant, detail = 0, 0, []
        for scenario in SCENARIOS:
            for algo in ALGOS:
                ccr = cells[(scenario, algo, "ccr")]["final"]["danger_frequency"]
                other = cells[(scenario, algo, base)]["final"]["danger_frequency"]
                is_lower = float(np.mean(ccr)) < float(np.mean(other))
                is_significant = is_lower and welch_significant(ccr, other)
                lower += is_lower
                significant += is_significant
                detail.append({"scenario": scenario, "algo": algo, "ccr": float(np.mean(ccr)),
                               base: float(np.mean(other)), "lower": is_lower,
                               "significant": is_significant})
        result[f"danger_lower_vs_{base}"] = {"cells": lower, "significant": significant,
                                             "of": 9, "detail": detail}
    raised = []
    for algo in ALGOS:
        for base in ("plain", "pessimistic"):
            ccr = cells[("hidden_obstacle", algo, "ccr")]["final"]["success_rate"]
            other = cells[("hidden_obstacle", algo, base)]["final"]["success_rate"]
            raised.append({"algo": algo, "vs": base, "ccr": float(np.mean(ccr)),
                           base: float(np.mean(other)),
                           "higher": float(np.mean(ccr)) > float(np.mean(other)),
                           "significant": float(np.mean(ccr)) > float(np.mean(other))
                           and welch_significant(ccr, other)})
    result["hidden_obstacle_success_raised"] = raised
    return result


def summary(cells, settings: Settings, invocations: list[dict[str, Any]]) -> dict[str, Any]:
    """Everything ``tables.json`` holds. ``invocations``: every run of this script that
    produced these cells (command, commit, wall time, programs trained), oldest first."""
    records = []
    for scenario in SCENARIOS:
        for algo in ALGOS:
            for variant in VARIANTS:
                cell = cells[(scenario, algo, variant)]
                record = {"scenario": scenario, "algo": algo, "variant": variant,
                          "seeds": cell["seeds"]}
                for metric in METRICS:
                    record[metric] = stats(cell["final"][metric])
                    paper = PAPER.get(metric, {}).get((scenario, algo, variant))
                    if paper is not None:
                        record[metric]["paper"] = paper
                records.append(record)
    ho = [cells[("hidden_obstacle", "maddpg", v)]["final"]["cumulative_danger_steps"]
          for v in ("ccr", "plain")]
    share = float(np.mean(ho[0]) / np.mean(ho[1])) if np.mean(ho[1]) > 0 else None
    headlines = {
        "danger_reduction_vs_plain": headline(cells, "danger_frequency", "ccr", "plain", -1),
        "danger_reduction_vs_pessimistic": headline(cells, "danger_frequency", "ccr",
                                                    "pessimistic", -1),
        "success_change_vs_pessimistic": headline(cells, "success_rate", "ccr", "pessimistic",
                                                  +1),
        "training_danger_share_maddpg_hidden_obstacle": {"mean": share},
    }
    programs = {(c["scenario"], c["algo"], c["variant"] == "ccr"): c for c in cells.values()}
    return {
        "settings": dataclasses.asdict(settings),
        "invocations": invocations,
        "programs_seconds": sum(c["train_seconds_of_program"] + c["compile_seconds_of_program"]
                                for c in programs.values()),
        "devices": [f"{d.platform}:{d.device_kind}" for d in jax.devices()],
        "jax_version": jax.__version__,
        "records": records,
        "headlines": headlines,
        "paper_headlines": PAPER_HEADLINES,
        "claims": claims(cells),
    }


# ---------------------------------------------------------------------------- writing
def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.2f}%"


def _cell_text(record_metric: dict, percent: bool) -> str:
    scale = 100.0 if percent else 1.0
    unit = "%" if percent else ""
    text = f"{record_metric['mean'] * scale:.2f}{unit}"
    if record_metric.get("half_width") is not None:
        text += f" ± {record_metric['half_width'] * scale:.2f}"
    if "paper" in record_metric:
        text += f" ({record_metric['paper'] * scale:.2f}{unit})"
    return text


def table(result: dict, metric: str, title: str, percent: bool) -> list[str]:
    by_key = {(r["scenario"], r["algo"], r["variant"]): r for r in result["records"]}
    header = "| | " + " | ".join(SCENARIO_NAMES[s] for s in SCENARIOS) + " |"
    lines = [f"### {title}", "", header, "|---|" + "---|" * len(SCENARIOS)]
    for algo in ALGOS:
        for variant in VARIANTS:
            name = LEARNER_NAMES[algo] + VARIANT_SUFFIX[variant]
            cells = [_cell_text(by_key[(s, algo, variant)][metric], percent) for s in SCENARIOS]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines + [""]


def tables_markdown(result: dict) -> str:
    settings = result["settings"]
    h = result["headlines"]
    p = result["paper_headlines"]
    lines = [
        "# The paper's Tables I and II, re-run with ccrjax",
        "",
        f"Made on {', '.join(result['devices'])} (jax {result['jax_version']}); the 18 "
        f"programs' compile and training time add up to {result['programs_seconds'] / 60:.1f} "
        "min. Runs of the script that made these results:",
        "",
        *(f"* `{run['command']}` at commit `{run['commit']}`, {run['date']}: trained "
          f"{run['programs_trained']} of 18 programs, wall time {run['wall_time_s'] / 60:.1f} min"
          + ("" if run.get("finished", True) else
             f" (stopped before the end{': ' + run['note'] if run.get('note') else ''})")
          for run in result["invocations"]),
        "",
        f"{settings['seeds']} seeds per cell (seeds {settings['seed_offset']} to "
        f"{settings['seed_offset'] + settings['seeds'] - 1}), {settings['steps']:,} environment "
        f"steps per run, CCR at lambda {settings['lam']:g}, pessimistic penalty "
        f"{settings['penalty']:g}; MAAC with {settings['maac_gradient_steps']} update(s) of batch "
        f"{settings['maac_batch_size']} per 100 steps. Each cell: the final evaluation "
        f"({settings['eval_episodes']} fresh episodes per seed, deterministic policies), mean "
        "± half-width of the 95% confidence interval over seeds (Student t), and in brackets "
        "the paper's number.",
        "",
    ]
    lines += table(result, "danger_frequency", "Table I: dangerous-behaviour frequency", True)
    lines += table(result, "success_rate", "Table II: success rate", True)
    lines += table(result, "hazard_distance", "Average distance to the hazard centre", False)
    lines += table(result, "return", "Return (environment reward per robot and episode)", False)
    lines += [
        "### The paper's headline figures, recomputed",
        "",
        "Averages over the 9 scenario x learner pairs of the relative change of the mean, as "
        "the paper computes them (its numbers follow from its tables this way); 95% "
        "bootstrap intervals over seeds.",
        "",
        "| figure | ours | paper |",
        "|---|---|---|",
    ]
    names = {
        "danger_reduction_vs_plain": "danger reduction, CCR vs plain",
        "danger_reduction_vs_pessimistic": "danger reduction, CCR vs pessimistic",
        "success_change_vs_pessimistic": "success change, CCR vs pessimistic",
        "training_danger_share_maddpg_hidden_obstacle":
            "cumulative training dangerous steps, MADDPG+CCR / MADDPG (hidden obstacle)",
    }
    for key, label in names.items():
        value = h[key]
        ours = _pct(value["mean"])
        if value.get("ci_low") is not None:
            ours += f" [{_pct(value['ci_low'])}, {_pct(value['ci_high'])}]"
        if value.get("left_out"):
            ours += f" ({value['left_out']} pair(s) with a zero base left out)"
        lines.append(f"| {label} | {ours} | {_pct(p[key])} |")
    c = result["claims"]
    lines += [
        "",
        "### Do the paper's claims hold here?",
        "",
        f"* CCR lowers the dangerous-behaviour frequency vs plain in "
        f"{c['danger_lower_vs_plain']['cells']} of 9 cells "
        f"({c['danger_lower_vs_plain']['significant']} significantly, Welch p < 0.05); "
        "the paper: 8 of 9.",
        f"* CCR lowers it vs pessimistic in {c['danger_lower_vs_pessimistic']['cells']} of 9 "
        f"({c['danger_lower_vs_pessimistic']['significant']} significantly); the paper: 9 of 9.",
        "* CCR's success rate on the hidden obstacle: "
        + "; ".join(
            f"{LEARNER_NAMES[r['algo']]} vs {r['vs']}: {_pct(r['ccr'])} vs {_pct(r[r['vs']])} "
            f"({'higher' if r['higher'] else 'not higher'}"
            f"{', significant' if r['significant'] else ''})"
            for r in c["hidden_obstacle_success_raised"]
        )
        + "; the paper: higher in all six.",
        "",
    ]
    return "\n".join(lines)


def draw_figures(cells, out: Path) -> list[Path]:
    from ccrjax.plots import Curves, draw_curves

    written = []
    plain = cells[("hidden_obstacle", "maddpg", "plain")]
    ccr = cells[("hidden_obstacle", "maddpg", "ccr")]
    curves = Curves()
    for label, cell in (("MADDPG", plain), ("MADDPG+CCR", ccr)):
        steps = np.asarray(cell["history"]["env_steps"][0])
        curves.add(label, steps, {m: np.asarray(cell["history"][m]) for m in
                                  ("danger_frequency", "success_rate", "cumulative_danger_steps")})
    path = out / "curves_hidden_obstacle_maddpg.png"
    draw_curves(curves, path, metrics=("danger_frequency", "success_rate",
                                       "cumulative_danger_steps"),
                title="hidden obstacle: MADDPG vs MADDPG+CCR during training")
    written.append(path)
    path = out / "trajectories_hidden_obstacle_maddpg.png"
    draw_trajectories(plain, ccr, path)
    written.append(path)
    path = out / "distance_hidden_obstacle_maddpg.png"
    draw_distances(plain, ccr, path)
    written.append(path)
    return written


def _record(cell: dict, title: str):
    from ccrjax.render import (
        CCR_STATE_COLOURS,
        CCR_STATE_NAMES,
        EpisodeRecord,
    )
    from ccrjax.scenarios import Layout

    episode = cell["episode"]
    positions = np.asarray(episode["position"])  # [T + 1, N, 2]
    states = np.zeros(positions.shape[:2], np.int32)
    if episode["ccr_state"] is not None:
        states[1:] = np.asarray(episode["ccr_state"])
    layout = Layout()
    return EpisodeRecord(
        scenario="hidden_obstacle", positions=positions, robot_radius=0.05,
        goal=layout.goal, goal_radius=layout.goal_radius,
        hazard_centre=np.asarray(episode["hazard_centre"]),
        hazard_half_extent=np.asarray(episode["hazard_half_extent"]),
        hazard_direction=np.zeros(2), states=states,
        state_names=CCR_STATE_NAMES, state_colours=CCR_STATE_COLOURS,
    )


def draw_trajectories(plain: dict, ccr: dict, path: Path) -> None:
    """The same evaluation episode (same starts, same obstacle) by both teams, side by side."""
    import tempfile

    from PIL import Image

    from ccrjax.render import draw_episode

    images = []
    with tempfile.TemporaryDirectory() as folder:
        for name, cell in (("plain", plain), ("ccr", ccr)):
            file = Path(folder) / f"{name}.png"
            draw_episode(_record(cell, name), file, dpi=90)
            images.append(Image.open(file).convert("RGB"))
        width = sum(image.width for image in images)
        height = max(image.height for image in images)
        canvas = Image.new("RGB", (width, height + 40), "white")
        from PIL import ImageDraw, ImageFont

        draw = ImageDraw.Draw(canvas)
        font = ImageFont.load_default(size=22)
        x = 0
        for image, label in zip(images, ("MADDPG (CCR not running: all standby)",
                                         "MADDPG+CCR (CCR's colours)"), strict=True):
            canvas.paste(image, (x, 40))
            draw.text((x + 20, 8), label, fill="black", font=font)
            x += image.width
        temporary = path.with_name(f".{path.stem}.tmp.png")
        canvas.save(temporary)
        temporary.replace(path)


def draw_distances(plain: dict, ccr: dict, path: Path) -> None:
    from ccrjax.plots import draw_obstacle_distances

    draw_obstacle_distances(plain["arrival"]["centre_distance"],
                            ccr["arrival"]["centre_distance"], path)


# ---------------------------------------------------------------------------- command
def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog="python experiments/tables.py", description=__doc__.split("\n")[0])
    defaults = Settings()
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=None,
                        help=f"seeds per cell (default: {defaults.seeds})")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=None,
                        help="first seed (default: 0); fresh seeds check our numbers")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help=f"environment steps per run (default: {defaults.steps:,})")
    parser.add_argument("--quick", action="store_true",
                        help="a tiny budget and tiny networks: checks the pipeline in minutes")
    parser.add_argument("--out", type=Path, default=None,
                        help=f"results folder (default: {RESULTS}; with --quick a temporary "
                        "folder must be given)")
    return parser


INVOCATIONS = "invocations.json"


def earlier_invocations(out: Path, settings: Settings) -> list[dict[str, Any]]:
    """The records of earlier runs of this script that made cells with these settings:
    from ``invocations.json`` (kept up to date while a run trains, so killed runs are
    there too), else from an older ``tables.json``; none when the settings changed."""
    for name in (INVOCATIONS, "tables.json"):
        try:
            old = json.loads((out / name).read_text())
        except (OSError, ValueError):
            continue
        if old.get("settings") == dataclasses.asdict(settings):
            return list(old.get("invocations", []))
        return []
    return []


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick and args.out is None:
        cli.fail("python experiments/tables.py",
                 "--quick needs --out: quick numbers must not replace the committed results")
    fields = dict(QUICK, quick=True) if args.quick else {}
    for name in ("seeds", "seed_offset", "steps"):
        if getattr(args, name) is not None:
            fields[name] = getattr(args, name)
    settings = Settings(**fields)
    out = args.out or RESULTS
    cli.enable_compilation_cache(cli.default_cache_dir())

    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    start = time.perf_counter()
    invocation = {
        "command": " ".join(["python experiments/tables.py",
                             *(argv if argv is not None else sys.argv[1:])]),
        "commit": git_commit(),  # the code this run trains with (+dirty: uncommitted changes)
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "finished": False,
    }
    out.mkdir(parents=True, exist_ok=True)
    previous = earlier_invocations(out, settings)

    def record(trained: int, finished: bool = False) -> None:
        # Rewritten after every program, so an invocation that is killed keeps its record.
        invocation.update(wall_time_s=time.perf_counter() - start, programs_trained=trained,
                          finished=finished)
        ledger = {"settings": dataclasses.asdict(settings),
                  "invocations": [*previous, invocation]}
        write_atomic(out / INVOCATIONS, json.dumps(ledger, indent=1) + "\n")

    record(0)
    cells, trained = run_grid(settings, out, log, record)
    record(trained, finished=True)
    result = summary(cells, settings, [*previous, invocation])
    write_atomic(out / "tables.json", json.dumps(result, indent=1) + "\n")
    write_atomic(out / "tables.md", tables_markdown(result))
    figures = draw_figures(cells, out)
    print(tables_markdown(result))
    print(f"wrote {out / 'tables.md'}, {out / 'tables.json'} and "
          + ", ".join(str(f) for f in figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
