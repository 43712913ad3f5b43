"""The paper's Tables I and II under a valid protocol: ``make tables``.

    python experiments/tables.py --out experiments/results/tables --force   # the grid
    python experiments/tables.py --out runs/tables                          # elsewhere
    python experiments/tables.py --quick --out /tmp/q     # a tiny budget, for the tests
    python experiments/tables.py --algos maac --scenarios turbulence --out runs/lane1
                                  # part of the grid (lanes); the tables once all 18 exist

Trains the grid 3 scenarios x 3 learners x 3 variants (plain, pessimistic, CCR) under
the protocol of ``docs/protocol.md`` (``experiments/protocol.py``): the tables' seeds
0-9, each learner's budget (chosen on the plain learners), learning from the 25,600th
transition, MAAC at 1 update of batch 256 every 100 steps (the protocol's amendment of
2026-11-25, from cost alone; the original's is 4 of batch 1024), CCR's lambda and the
pessimistic penalty as selected by their searches (``experiments/search.py``, on the
disjoint selection seeds; ``--lam`` and ``--penalty`` override). Per scenario and
learner, two programs: plain and pessimistic together (plain is the pessimistic transform
with penalty 0, exactly), and CCR; each trains all its runs at once, sharded over every
device (:mod:`ccrjax.training.grid`); while one program trains, the next one compiles.

Cost, measured on this project's 2-core CPU (2 cores, no GPU). The grid is 18 programs,
270 runs of 3,000,000 environment steps (30 per scenario and learner: 3 variants x 10
seeds). A run costs about 4 to 6.5 minutes of the whole CPU for IDDPG, 7 for MADDPG and 7
to 9 for MAAC at the protocol's 1 x 256 (``benchmarks/train_throughput.py``: one IDDPG seed
alone 12,500 environment steps per second, 2026-11-24, commit ``8ee8675``; 3 seeds in one
program, 2026-11-25, commit ``4cb49df``: MADDPG 7,200 and MAAC 5,800 in all; the lambda
search's CCR IDDPG program of 21 runs, 2h15m alone on 2026-11-23; MAAC search parts of 4
and 5 runs, two programs side by side on the two cores, 58 and 73 minutes on 2026-11-26,
about 7.3 minutes of the whole CPU per run), so the whole grid takes about 6 to 10 h
(IDDPG) + 10.5 h (MADDPG) + 11 to 13 h (MAAC): about 28 to 33 hours of this CPU, made in
parts over several sessions (``docs/experiments.md``). On a GPU it is far shorter: the
committed grid was made on an H100 on 2026-11-26 in 30m40s of programs (compiling and
training; 83 s to 4.2 minutes per scenario and learner, both programs), in two sessions.
At ``--steps 6000000`` (the tables beside the searches at 6M) every run has twice the
steps. Measured (``experiments/results/tables_6m``, 2026-11-29 and 30): the 12 IDDPG and
MADDPG programs, made on this CPU in two-seed parts run two or three side by side, trained
21.3 h (IDDPG) and 33.4 h (MADDPG) in all, about 10.6 and 14.9 hours of wall; MAAC's two
parts side by side trained 7 of 60 evaluations in 15 minutes, about 24 hours of wall for
its 6 programs, so about 50 hours for the grid here (the CPU's speed varied 2.4 times
between sessions). An H200 made those 6 MAAC programs in 12 minutes, one lane per scenario.
Cells are resumable across invocations, so the grid can be spread over several; the
program in training is checkpointed every ``--checkpoint-minutes`` into ``<out>/partial/``
and resumed from there (:mod:`ccrjax.run.grid_checkpoint`).

A program too long for one sitting (on this project's 2-core CPU the MAAC and MADDPG
plain-and-pessimistic programs take 2 to 3 hours, and partial checkpoints stay on the machine
that made them) can be made in parts: ``--part-seeds 0 1 2 3 4`` trains those seeds alone
and keeps each variant's part in ``<out>/parts/``; once a cell's parts cover its seeds they
are joined into it (each run depends only on its seed and parameters: the runs one program
holds, to float32 rounding) and deleted.

Every finished cell (scenario, learner, variant) is written atomically to
``<out>/cells/<scenario>-<algo>-<variant>.json``: per-seed final evaluations and
curves, whether the return plateaued (:func:`ccrjax.run.stats.plateau`), the first
iteration whose updates went non-finite per seed (-1: none; such a run is kept, its bad
updates skipped, and named in ``tables.md``), the behaviour measurements, and the
program's wall time, device and commit. A re-run skips the cells
made with the same settings. Every invocation is recorded in ``<out>/invocations.json``
(:mod:`ledger`). ProgramProgress lines estimate the time left across programs. Then:

* ``tables.md`` and ``tables.json``: Tables I and II in the paper's layout with the
  reference controllers' rows (go-to-goal, oracle), the final distance, the hazard
  distance and the return; per cell the mean and Student-t 95% interval over seeds
  (clipped to the metric's range), the paper's number, and Welch tests of CCR against
  plain and pessimistic (significant cells marked); rliable's aggregate view over the 9
  scenario x learner pairs (interquartile mean with stratified-bootstrap intervals, the
  probability of improvement of CCR over each baseline, for danger and success); the
  paper's headline numbers recomputed (with bootstrap intervals); the claim scorecard;
* figures: ``progress_<scenario>.png`` (danger against return along training, every
  variant and learner, with bands: is CCR's safety bought by slower progress?),
  ``curves_<scenario>_<algo>.png`` (return, danger, success and the dangerous steps since
  learning started along training, the three variants, every pair),
  ``trajectories_hidden_obstacle_maddpg.png``, ``distance_hidden_obstacle_maddpg.png``.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/tables.py")

import argparse
import dataclasses
import json
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ccrjax import cli
from ccrjax.envs.scenarios import Layout
from ccrjax.run.folder import (
    METRIC_RANGES,
    POINT_METRICS,
    git_commit,
    replacing,
    write_atomic,
)
from ccrjax.run.stats import (
    format_mean_ci,
    holm,
    iqm,
    mean_ci,
    mean_relative_change,
    plateau_or_undetermined,
    probability_of_improvement,
    welch,
)
from ccrjax.run.sweep_grid import nonfinite_runs, nonfinite_text
from ccrjax.training import ALGOS, TrainConfig, make_env
from ccrjax.training.grid import GridRuns, GridTraining
from ccrjax.transforms import Pessimistic
from ccrjax.transforms.ccr import CCR, CCRConfig
from ccrjax.viz.analysis import arrival_analysis, followers_closest
from ccrjax.viz.plots import (
    VARIANT_COLOURS,
    Curves,
    draw_curves,
    draw_obstacle_distances,
    draw_progress_matched,
)
from ccrjax.viz.record import CCR_STATE_COLOURS, CCR_STATE_NAMES, EpisodeRecord
from ccrjax.viz.render import draw_episode
from experiments import protocol
from experiments.ledger import (
    RESULTS,
    STOPPED_KEPT,
    Ledger,
    Partial,
    ProgramProgress,
    add_checkpoint_option,
    add_no_train_option,
    add_out_options,
    cell_is_current,
    check_quick_out,
    device_name,
    discard_parts,
    duration,
    invocation_line,
    joined_by_seed,
    log,
    made_parts,
    open_experiment,
    part_made,
    part_path,
    part_seeds_from,
    part_settings,
    parts_cover,
    parts_made_text,
    read_json,
    refuse_untrained,
    seed_order,
    settings_record,
    training_record,
)
from experiments.paper import PAPER, PAPER_HEADLINES, PAPER_OBSTACLE_DISTANCE_RATIO, PAPER_SCENARIOS
from experiments.reference_controllers import evaluate_controller

PROG = "python experiments/tables.py"
VARIANTS = ("plain", "pessimistic", "ccr")
LEARNER_NAMES = protocol.LEARNER_NAMES
VARIANT_SUFFIX = {"plain": "", "pessimistic": " (Pessimistic)", "ccr": "+CCR"}
SCENARIO_NAMES = {"hidden_obstacle": "hidden obstacle", "turbulence": "turbulence",
                  "strong_wind": "strong wind"}
CONTROLLERS = {"go_to_goal": "go-to-goal (reference)", "oracle": "oracle (reference)"}
METRICS = POINT_METRICS
SEARCHES = RESULTS / "search"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings(protocol.Settings):
    """What every cell is trained with (a cell made with other settings is redone); the
    tables need all 18 programs, which may come from several invocations."""

    lam: float  # CCR's lambda (the search's selection)
    penalty: float  # the pessimistic penalty (the search's selection)
    seeds: tuple[int, ...] = protocol.TABLE_SEEDS
    behaviour_episodes: int = 64  # episodes of the behaviour analysis per seed
    controller_episodes: int = 1024  # episodes of each reference controller

    def config(self, scenario: str, algo: str, variant: str) -> TrainConfig:
        transform = {"plain": None, "pessimistic": Pessimistic(penalty=self.penalty),
                     "ccr": CCR(CCRConfig(lam=self.lam))}[variant]
        return protocol.run_config(self, scenario, algo, variant, transform=transform)


QUICK = dict(steps=protocol.QUICK_STEPS, seeds=(0, 1), eval_every=protocol.QUICK_EVAL_EVERY,
             eval_episodes=protocol.QUICK_EVAL_EPISODES, behaviour_episodes=4,
             controller_episodes=16)


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


def variant_cell_path(out: Path, scenario: str, algo: str, variant: str) -> Path:
    return out / "cells" / f"{cell_stem(scenario, algo, variant)}.json"


def read_cell(path: Path, settings: Settings) -> dict | None:
    """A finished cell made with ``settings``, or None."""
    cell = read_json(path)
    return cell if cell_is_current(cell, settings_record(settings)) else None


def build_training(job: Job, settings: Settings) -> GridTraining:
    seeds = list(settings.seeds)
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
    seeds = list(settings.seeds)
    cells = {}
    for index, variant in enumerate(job.variants):
        part = runs.select(np.arange(len(runs.seeds)) // len(seeds) == index)
        final = part.final
        cell = {
            "scenario": job.scenario, "algo": job.algo, "variant": variant,
            "settings": settings_record(settings), "budget": settings.budget(job.algo),
            "training": training_record(settings.config(job.scenario, job.algo, variant)),
            "seeds": part.seeds,
            "params": {k: [float(x) for x in v] for k, v in part.params.items()},
            "final": {m: [float(x) for x in final[m]] for m in METRICS},
            "history": {m: part.history[m].tolist() for m in (*METRICS, "env_steps")},
            "return_plateau": plateau_or_undetermined(part.history["return"]),
            "nonfinite_iteration": part.nonfinite_iteration.tolist(),
            "train_seconds_of_program": runs.run_s,
            "compile_seconds_of_program": runs.compile_s,
            "device": device_name(), "commit": git_commit(),
            "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        }
        episodes = part.episodes
        if job.scenario == "hidden_obstacle":
            analysis = arrival_analysis(episodes, reach=0.3)
            cell["arrival"] = {  # per seed and arrival rank, means over episodes
                "closest": analysis["closest"].mean(axis=1).tolist(),
                "centre_distance": analysis["centre_distance"].mean(axis=1).tolist(),
                "followers_closest_successful": followers_closest(analysis).tolist(),
            }
        cell["episode"] = {  # the first recorded episode of the first seed, for pictures
            "position": episodes["position"][0, ..., 0].tolist(),
            "success": episodes["success"][0, :, 0].tolist(),
            "danger": (episodes["danger"][0, ..., 0] > 0).tolist(),  # [T, N]
            "hazard_centre": episodes["hazard_centre"][0, :, 0].tolist(),
            "hazard_half_extent": episodes["hazard_half_extent"][0, :, 0].tolist(),
            "ccr_state": (episodes["ccr_state"][0, ..., 0].tolist()
                          if "ccr_state" in episodes else None),
        }
        cells[variant] = cell
    return cells


def grid_jobs() -> list[Job]:
    """The whole grid's 18 programs."""
    return [Job(scenario, algo, variants) for scenario in PAPER_SCENARIOS for algo in ALGOS
            for variants in (("plain", "pessimistic"), ("ccr",))]


def jobs_of(settings: Settings) -> list[Job]:
    """The programs this invocation trains: ``settings.scenarios`` x ``settings.algos``."""
    return [job for job in grid_jobs()
            if job.scenario in settings.scenarios and job.algo in settings.algos]


def job_cells(out: Path, job: Job, settings: Settings) -> dict[str, dict] | None:
    """A program's cells in ``out`` by variant, if all were made with ``settings``."""
    found = [read_cell(variant_cell_path(out, job.scenario, job.algo, v), settings)
             for v in job.variants]
    return dict(zip(job.variants, found, strict=True)) if all(found) else None


def grid_cells(out: Path, settings: Settings) -> tuple[dict, list[str]]:
    """Every cell of the whole grid found in ``out`` by (scenario, algo, variant), and the
    names of the programs still missing."""
    cells, missing = {}, []
    for job in grid_jobs():
        found = job_cells(out, job, settings)
        if found is None:
            missing.append(job.name)
        else:
            cells.update({(job.scenario, job.algo, v): c for v, c in found.items()})
    return cells, missing


def cell_stem(scenario: str, algo: str, variant: str) -> str:
    """A cell's name: its file in ``cells/``, and its parts' in ``parts/``."""
    return f"{scenario}-{algo}-{variant}"


def job_part_made(out: Path, job: Job, settings: Settings, seeds: tuple[int, ...]) -> bool:
    """Whether every variant of ``job`` has its part on ``seeds`` in ``out``."""
    return all(part_made(settings, out, cell_stem(job.scenario, job.algo, variant), seeds)
               for variant in job.variants)


def join_cell_parts(settings: Settings, parts: list[dict[str, Any]]) -> dict[str, Any] | None:
    """A variant's cell joined from ``parts`` (its cells on disjoint seeds), or ``None``
    while they do not cover ``settings.seeds`` exactly once: every per-seed record in the
    order of ``settings.seeds``, the plateau check made again over all seeds, the episode
    of the first seed (as one program keeps it), the programs' times added up, and which
    seeds were made where, when and at which commit."""
    if not parts_cover(settings, parts):
        return None
    order = seed_order(parts, settings.seeds)

    def joined(records: list[list[Any]]) -> list[Any]:
        return joined_by_seed(records, order)

    first = parts[0]
    history = {m: joined([part["history"][m] for part in parts]) for m in first["history"]}
    times = ("train_seconds_of_program", "compile_seconds_of_program")
    cell = {
        **{k: first[k] for k in ("scenario", "algo", "variant", "budget", "training")},
        "settings": settings_record(dataclasses.replace(settings, part_seeds=())),
        "seeds": list(settings.seeds),
        **{group: {k: joined([part[group][k] for part in parts]) for k in first[group]}
           for group in ("params", "final")},
        "history": history,
        "return_plateau": plateau_or_undetermined(np.asarray(history["return"])),
        "nonfinite_iteration": joined([part["nonfinite_iteration"] for part in parts]),
        **{k: sum(part[k] for part in parts) for k in times},
        **parts_made_text(parts, times),
    }
    if "arrival" in first:
        cell["arrival"] = {k: joined([part["arrival"][k] for part in parts])
                           for k in first["arrival"]}
    cell["episode"] = parts[order[0][0]]["episode"]
    return cell


def join_parts_of(jobs: list[Job], settings: Settings, out: Path) -> None:
    """Joins every variant of ``jobs`` whose parts in ``out`` cover its seeds into its cell,
    deleting the parts; says what each still lacks."""
    for job in jobs:
        for variant in job.variants:
            stem = cell_stem(job.scenario, job.algo, variant)
            parts = made_parts(settings, out, stem)
            cell = join_cell_parts(settings, parts) if parts else None
            if cell is None:
                made = sorted(seed for part in parts for seed in part["seeds"])
                log(f"{stem}: parts made on seeds {made} of {list(settings.seeds)}")
                continue
            write_atomic(variant_cell_path(out, job.scenario, job.algo, variant),
                         json.dumps(cell) + "\n")
            discard_parts(out, stem, parts)
            log(f"{stem}: joined from {len(parts)} parts into its cell")


def run_grid(settings: Settings, out: Path, ledger: Ledger, partial: Partial) -> int:
    """Trains every missing program of ``settings`` (compiling the next program while one
    trains), or with ``settings.part_seeds`` its part on those seeds, then joins the parts
    that cover their cells' seeds; returns the number of programs trained."""
    jobs = jobs_of(settings)
    todo = [job for job in jobs if job_cells(out, job, settings) is None]
    seeds = settings.part_seeds or settings.seeds
    trained = part_settings(settings, seeds) if settings.part_seeds else settings
    budgets = f"budgets { {a: settings.budget(a) for a in ALGOS} }, on {device_name()}"
    missing = todo
    if settings.part_seeds:
        todo = [job for job in missing if not job_part_made(out, job, settings, seeds)]
        log(f"{len(jobs) - len(missing)} of {len(jobs)} programs already done; of the other "
            f"{len(missing)}, {len(missing) - len(todo)} made on seeds {list(seeds)}; "
            f"{len(todo)} parts to train ({len(seeds)} seeds per cell, {budgets})")
    else:
        log(f"{len(jobs) - len(todo)} of {len(jobs)} programs already done; {len(todo)} to "
            f"train ({len(seeds)} seeds per cell, {budgets})")
    progress = ProgramProgress([(job.name, job.algo,
                          len(job.variants) * len(seeds) * settings.budget(job.algo))
                         for job in todo])
    (out / "cells").mkdir(parents=True, exist_ok=True)
    # Compilation runs ahead in worker threads (XLA's compiler releases the GIL) while the
    # main thread trains; the quick mode's programs run for moments, so there it compiles
    # on both cores at XLA's lowest optimisation level.
    workers = 2 if settings.quick else 1
    with ThreadPoolExecutor(max_workers=workers) as compiler:
        for job in todo:
            job.training = build_training(job, trained)
        compiled = [compiler.submit(job.training.compile, not settings.quick) for job in todo]
        for number, (job, done) in enumerate(zip(todo, compiled, strict=True)):
            done.result()
            name = (part_path(out, job.name, seeds).stem if settings.part_seeds
                    else job.name)
            runs = partial.train(job.training, name)
            for variant, cell in cells_of(job, runs, trained).items():
                path = (part_path(out, cell_stem(job.scenario, job.algo, variant), seeds)
                        if settings.part_seeds else
                        variant_cell_path(out, job.scenario, job.algo, variant))
                path.parent.mkdir(exist_ok=True)
                write_atomic(path, json.dumps(cell) + "\n")
            partial.discard(name)
            job.training = None  # free the compiled program
            ledger.record(number + 1)
            log(progress.finished(number, runs.run_s + runs.compile_s))
    if settings.part_seeds:
        join_parts_of(missing, settings, out)
    return len(todo)


def reference_rows(settings: Settings) -> dict[tuple[str, str], dict[str, float]]:
    """The reference controllers' metrics per (scenario, controller), over
    ``controller_episodes`` fresh episodes (no training, no seeds)."""
    rows = {}
    key = jax.random.PRNGKey(2**30 + 12)
    for scenario in PAPER_SCENARIOS:
        env = make_env(settings.config(scenario, "maddpg", "plain"),
                       settings.controller_episodes)
        for name in CONTROLLERS:
            metrics = evaluate_controller(env, name, key)
            rows[(scenario, name)] = {m: float(v) for m, v in metrics.items()}
    return rows


# ---------------------------------------------------------------------------- the numbers
def stats(values: list[float], metric: str) -> dict[str, Any]:
    return {"per_seed": values, **mean_ci(values, bounds=METRIC_RANGES[metric])}


# The paper's averaged relative changes: (metric, new, base, sign, scenarios), the average
# over those scenarios' scenario x learner pairs (sign -1: a reduction).
HEADLINES = {
    "danger_reduction_vs_plain": ("danger_frequency", "ccr", "plain", -1.0, PAPER_SCENARIOS),
    "danger_reduction_vs_pessimistic": ("danger_frequency", "ccr", "pessimistic", -1.0,
                                        PAPER_SCENARIOS),
    "success_change_vs_pessimistic": ("success_rate", "ccr", "pessimistic", 1.0, PAPER_SCENARIOS),
    "success_change_vs_plain_turbulence": ("success_rate", "ccr", "plain", 1.0,
                                           ("turbulence",)),
}


def headline(cells, metric: str, new: str, base: str, sign: float,
             scenarios: tuple[str, ...] = PAPER_SCENARIOS, resamples: int = 2000,
             seed: int = 0) -> dict[str, Any]:
    """The paper's averaged relative change over the ``scenarios``' scenario x learner
    pairs (:func:`ccrjax.run.stats.mean_relative_change`), with the pairs named."""
    names = [(s, a) for s in scenarios for a in ALGOS]
    pairs = [(np.asarray(cells[(s, a, new)]["final"][metric]),
              np.asarray(cells[(s, a, base)]["final"][metric])) for s, a in names]
    result = mean_relative_change(pairs, sign, resamples=resamples, seed=seed)
    result["pair_names"] = [f"{SCENARIO_NAMES[s]}, {LEARNER_NAMES[a]}" for s, a in names]
    return result


def obstacle_distance_ratio(cells) -> dict[str, Any]:
    """MADDPG+CCR's average distance to the obstacle's centre over MADDPG's, robot by
    robot in arrival order (means over seeds of the per-seed means over episodes), on the
    hidden obstacle: the paper's "1.2x to 4.7x"."""
    plain, ccr = (np.asarray(cells[("hidden_obstacle", "maddpg", v)]["arrival"]
                             ["centre_distance"]).mean(axis=0) for v in ("plain", "ccr"))
    ratio = ccr / plain
    return {"by_rank": ratio.tolist(), "low": float(ratio.min()), "high": float(ratio.max()),
            "paper": list(PAPER_OBSTACLE_DISTANCE_RATIO)}


def welch_marks(cells) -> dict[tuple[str, str, str, str], dict]:
    """Welch tests of CCR against plain and pessimistic, per cell and metric."""
    marks = {}
    for scenario in PAPER_SCENARIOS:
        for algo in ALGOS:
            ccr = cells[(scenario, algo, "ccr")]["final"]
            for base in ("plain", "pessimistic"):
                other = cells[(scenario, algo, base)]["final"]
                for metric in ("danger_frequency", "success_rate"):
                    marks[(scenario, algo, base, metric)] = welch(ccr[metric], other[metric])
    return marks


def claims(cells, marks) -> dict[str, Any]:
    """The direction of the paper's claims, checked cell by cell (the scorecard)."""
    result: dict[str, Any] = {}
    for base in ("plain", "pessimistic"):
        lower, significant, detail = 0, 0, []
        for scenario in PAPER_SCENARIOS:
            for algo in ALGOS:
                ccr = float(np.mean(cells[(scenario, algo, "ccr")]["final"]["danger_frequency"]))
                other = float(np.mean(cells[(scenario, algo, base)]["final"]["danger_frequency"]))
                is_lower = ccr < other
                is_significant = is_lower and marks[(scenario, algo, base,
                                                     "danger_frequency")]["significant"]
                lower += is_lower
                significant += is_significant
                detail.append({"scenario": scenario, "algo": algo, "ccr": ccr, base: other,
                               "lower": is_lower, "significant": is_significant})
        # The 9 cells' tests as one family (Holm): how many lower cells survive it.
        p_values = [marks[(d["scenario"], d["algo"], base, "danger_frequency")]["p"]
                    for d in detail]
        for d, rejected in zip(detail, holm(p_values), strict=True):
            d["significant_holm"] = bool(d["lower"] and rejected)
        result[f"danger_lower_vs_{base}"] = {
            "cells": lower, "significant": significant,
            "significant_holm": sum(d["significant_holm"] for d in detail),
            "of": 9, "detail": detail}
    raised = []
    for algo in ALGOS:
        ccr = float(np.mean(cells[("hidden_obstacle", algo, "ccr")]["final"]["success_rate"]))
        both = []
        for base in ("plain", "pessimistic"):
            other = float(np.mean(cells[("hidden_obstacle", algo, base)]["final"]["success_rate"]))
            mark = marks[("hidden_obstacle", algo, base, "success_rate")]
            both.append({"vs": base, "ccr": ccr, "other": other, "higher": ccr > other,
                         "significant": ccr > other and mark["significant"]})
        raised.append({"algo": algo, "against": both,
                       "above_both": all(b["higher"] for b in both),
                       "significantly_above_both": all(b["significant"] for b in both)})
    result["hidden_obstacle_success_above_both"] = {
        "learners": sum(r["above_both"] for r in raised),
        "significant": sum(r["significantly_above_both"] for r in raised),
        "of": 3, "detail": raised}
    return result


def aggregates(cells, resamples: int = 2000) -> dict[str, Any]:
    """rliable over the 9 scenario x learner pairs (tasks), seeds as runs: each variant's
    IQM of danger and of success, and the probability that CCR improves on each baseline
    (lower danger, higher success)."""
    pairs = [(s, a) for s in PAPER_SCENARIOS for a in ALGOS]
    result: dict[str, Any] = {}
    for metric, sign in (("danger_frequency", -1.0), ("success_rate", 1.0)):
        scores = {v: np.array([cells[(s, a, v)]["final"][metric] for s, a in pairs]).T
                  for v in VARIANTS}  # [seeds, 9]
        result[metric] = {
            "iqm": iqm(scores, resamples=resamples),
            "probability_of_improvement": {
                base: probability_of_improvement(sign * scores["ccr"], sign * scores[base],
                                                 resamples=resamples)
                for base in ("plain", "pessimistic")},
        }
    return result


def training_danger_share(cells) -> dict[str, Any]:
    """MADDPG+CCR's dangerous robot-steps during training from the start of learning, as a
    share of plain MADDPG's, on the hidden obstacle (the paper's 28.09%)."""
    ccr, plain = (np.asarray(cells[("hidden_obstacle", "maddpg", v)]["final"]
                             ["learning_danger_steps"]) for v in ("ccr", "plain"))
    share = mean_relative_change([(ccr, plain)], +1.0)
    return {"mean": None if share["mean"] is None else 1.0 + share["mean"],
            "ci_low": None if share["ci_low"] is None else 1.0 + share["ci_low"],
            "ci_high": None if share["ci_high"] is None else 1.0 + share["ci_high"]}


def summary(cells, settings: Settings, invocations: list[dict[str, Any]],
            controllers: dict, sources: dict[str, str]) -> dict[str, Any]:
    """Everything ``tables.json`` holds."""
    marks = welch_marks(cells)
    records = []
    for scenario in PAPER_SCENARIOS:
        for algo in ALGOS:
            for variant in VARIANTS:
                cell = cells[(scenario, algo, variant)]
                record = {"scenario": scenario, "algo": algo, "variant": variant,
                          "seeds": cell["seeds"], "return_plateau": cell["return_plateau"],
                          "nonfinite_iteration": cell.get("nonfinite_iteration"),
                          "program_seconds": cell["train_seconds_of_program"]
                          + cell["compile_seconds_of_program"],
                          "device": cell["device"], "commit": cell["commit"]}
                for metric in METRICS:
                    record[metric] = stats(cell["final"][metric], metric)
                    paper = PAPER.get(metric, {}).get((scenario, algo, variant))
                    if paper is not None:
                        record[metric]["paper"] = paper
                    if variant == "ccr" and metric in ("danger_frequency", "success_rate"):
                        record[metric]["welch"] = {
                            base: marks[(scenario, algo, base, metric)]
                            for base in ("plain", "pessimistic")}
                if "arrival" in cell:
                    measured = [x for x in cell["arrival"]["followers_closest_successful"]
                                if np.isfinite(x)]  # seeds with a successful follower
                    values = measured or [float("nan")]
                    record["followers_closest_successful"] = {  # signed: no range to clip to
                        "per_seed": values, **mean_ci(values),
                        "seeds_measured": f"{len(measured)}/{len(cell['seeds'])}"}
                records.append(record)
    headlines = {key: headline(cells, *definition) for key, definition in HEADLINES.items()}
    headlines["training_danger_share_maddpg_hidden_obstacle"] = training_danger_share(cells)
    programs = {(c["scenario"], c["algo"], c["variant"] == "ccr"): c for c in cells.values()}
    return {
        "settings": settings_record(settings),
        "sources": sources,
        "budgets": {a: settings.budget(a) for a in ALGOS},
        "invocations": invocations,
        "programs_seconds": sum(c["train_seconds_of_program"] + c["compile_seconds_of_program"]
                                for c in programs.values()),
        "devices": sorted({c["device"] for c in cells.values()}),
        "commits": sorted({str(c["commit"]) for c in cells.values()}),
        "records": records,
        "controllers": [{"scenario": s, "controller": c, **m}
                        for (s, c), m in controllers.items()],
        "nonfinite": [line for (s, a, v), cell in cells.items() for line in nonfinite_runs(
            cell, f"{SCENARIO_NAMES[s]}, {LEARNER_NAMES[a]}{VARIANT_SUFFIX[v]}")],
        "runs": sum(len(cell["seeds"]) for cell in cells.values()),
        "headlines": headlines,
        "paper_headlines": PAPER_HEADLINES,
        "obstacle_distance_ratio_maddpg": obstacle_distance_ratio(cells),
        "aggregates": aggregates(cells),
        "claims": claims(cells, marks),
    }


# ---------------------------------------------------------------------------- writing
def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.2f}%"


def welch_symbols(marks: dict) -> str:
    """``↓*`` / ``↑*``: CCR significantly below / above plain; ``↓†`` / ``↑†``: below /
    above pessimistic (Welch, p < 0.05); nothing where the difference is not significant."""
    text = ""
    for base, symbol in (("plain", "*"), ("pessimistic", "†")):
        mark = marks.get(base, {})
        if mark.get("significant"):
            text += (" ↓" if mark["difference"] < 0 else " ↑") + symbol
    return text


def _cell_text(record_metric: dict, percent: bool, digits: int = 2) -> str:
    scale, unit = (100.0, "%") if percent else (1.0, "")
    text = (format_mean_ci(record_metric, percent, digits) if np.isfinite(record_metric["mean"])
            else "none")
    if "seeds_measured" in record_metric:
        text += f" (n={record_metric['seeds_measured']})"
    text += welch_symbols(record_metric.get("welch", {}))
    if "paper" in record_metric:
        text += f" ({record_metric['paper'] * scale:.2f}{unit})"
    return text


def table(result: dict, metric: str, title: str, percent: bool, digits: int = 2) -> list[str]:
    by_key = {(r["scenario"], r["algo"], r["variant"]): r for r in result["records"]}
    controllers = {(c["scenario"], c["controller"]): c for c in result["controllers"]}
    header = "| | " + " | ".join(SCENARIO_NAMES[s] for s in PAPER_SCENARIOS) + " |"
    lines = [f"### {title}", "", header, "|---|" + "---|" * len(PAPER_SCENARIOS)]
    for name, label in CONTROLLERS.items():
        if metric not in controllers[(PAPER_SCENARIOS[0], name)]:
            continue  # a training count: the controllers do not train
        scale, unit = (100.0, "%") if percent else (1.0, "")
        lines.append(f"| {label} | " + " | ".join(
            f"{controllers[(s, name)][metric] * scale:.2f}{unit}" for s in PAPER_SCENARIOS) + " |")
    for algo in ALGOS:
        for variant in VARIANTS:
            name = LEARNER_NAMES[algo] + VARIANT_SUFFIX[variant]
            cells = [_cell_text(by_key[(s, algo, variant)][metric], percent, digits)
                     for s in PAPER_SCENARIOS]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines + [""]


def _interval(value: dict, key: str = "mean") -> str:
    text = _pct(value.get(key))
    if value.get("ci_low") is not None:
        text += f" [{_pct(value['ci_low'])}, {_pct(value['ci_high'])}]"
    return text


def tables_markdown(result: dict) -> str:
    settings = result["settings"]
    h = result["headlines"]
    p = result["paper_headlines"]
    seeds = settings["seeds"]
    lines = [
        "# The paper's Tables I and II, re-run with ccrjax",
        "",
        *([protocol.quick_note(), ""] if settings.get("quick") else []),
        f"Made on {', '.join(result['devices'])} at commit(s) "
        f"{', '.join(f'`{c}`' for c in result['commits'])}; the 18 programs' compile and "
        f"training time add up to {duration(result['programs_seconds'])}. Invocations:",
        "",
        *(invocation_line(run, 18) for run in result["invocations"]),
        "",
        f"{len(seeds)} seeds per cell (seeds {seeds[0]} to {seeds[-1]}); environment steps per "
        f"run {result['budgets']}; CCR at lambda {settings['lam']:g} "
        f"({result['sources']['lam']}), pessimistic penalty {settings['penalty']:g} "
        f"({result['sources']['penalty']}). Each cell: the final evaluation "
        f"({settings['eval_episodes']} fresh episodes per seed, deterministic policies), the "
        "mean and its 95% confidence interval over seeds (Student t, clipped to the metric's "
        "range); after a CCR cell, `↓*` / `↑*`: CCR significantly below / above plain, `↓†` / "
        "`↑†`: below / above pessimistic (Welch, p < 0.05, each test alone: 36 of them; a "
        "seed's three variants share their evaluation episodes, and plain and pessimistic "
        "their initial parameters (CCR's networks also read the shared scores), a pairing "
        "these unpaired tests ignore: conservative where the variants' results "
        "correlate); in parentheses the paper's number (IDDPG is the paper's DDPG: one "
        "DDPG per robot). Reference rows: hand-written "
        f"controllers over {settings['controller_episodes']} episodes (no learning).",
        "",
    ]
    lines += table(result, "danger_frequency", "Table I: dangerous-behaviour frequency", True)
    lines += table(result, "success_rate", "Table II: success rate", True)
    lines += table(result, "target_distance", "Final distance to the target", False)
    lines += table(result, "hazard_distance", "Average distance to the hazard centre", False)
    lines += table(result, "return", "Return (environment reward per robot and episode)", False)
    lines += table(result, "learning_danger_steps", "Dangerous robot-steps during training, "
                   "from the start of learning to the end (the paper's cumulative training "
                   "danger)", False, digits=0)
    by_key = {(r["scenario"], r["algo"], r["variant"]): r for r in result["records"]}
    lines += [
        "### Behaviour on the hidden obstacle",
        "",
        "The followers' closest approach to the obstacle's surface: every robot but the first "
        "to arrive, counting only robots that end in the target area (keeping away by giving "
        "up does not count); mean over the seeds that had such a follower (n: those seeds of "
        "all), 95% CI. The paper: with CCR the followers steer away before touching.",
        "",
        "| | " + " | ".join(VARIANTS) + " |",
        "|---|" + "---|" * len(VARIANTS),
    ]
    for algo in ALGOS:
        lines.append(f"| {LEARNER_NAMES[algo]} | " + " | ".join(
            _cell_text(by_key[("hidden_obstacle", algo, v)]["followers_closest_successful"],
                       False) for v in VARIANTS) + " |")
    lines.append("")
    plain_records = [r for r in result["records"] if r["variant"] == "plain"]
    not_levelled = [r for r in plain_records if r["return_plateau"].get("plateaued") is False]
    undetermined = [r for r in plain_records if r["return_plateau"].get("plateaued") is None]
    lines += [
        "### Did the plain learners converge?",
        "",
        "The plain learner's evaluated return has plateaued if the mean of its last 20% of "
        "evaluations lies within the 95% interval of the 20% before (passing means the test "
        "found no rise: a slow rise smaller than that interval passes). "
        + _convergence_text(not_levelled, undetermined),
        "",
        *plateau_table(plain_records),
        "### Did training stay finite?",
        "",
        nonfinite_text(result["nonfinite"], f"the {result['runs']} runs"),
        "",
        "### Aggregates over the 9 scenario x learner pairs (rliable)",
        "",
        "Interquartile mean over seeds x pairs with 95% stratified-bootstrap intervals, and "
        "the probability that a CCR run improves on a baseline run of the same pair (lower "
        "danger, higher success; 0.5 = no difference).",
        "",
        "| | IQM danger | IQM success | P(CCR safer) | P(CCR more successful) |",
        "|---|---|---|---|---|",
    ]
    agg = result["aggregates"]
    for variant in VARIANTS:
        danger = agg["danger_frequency"]["iqm"][variant]
        success = agg["success_rate"]["iqm"][variant]
        if variant == "ccr":
            improve = ("", "")
        else:
            improve = tuple(
                _probability(agg[m]["probability_of_improvement"][variant])
                for m in ("danger_frequency", "success_rate"))
        lines.append(f"| {variant} | {_interval(danger, 'iqm')} | {_interval(success, 'iqm')} | "
                     f"{improve[0]} | {improve[1]} |")
    lines += [
        "",
        "### The paper's headline figures, recomputed",
        "",
        "Averages over the scenario x learner pairs (all 9, or turbulence's 3) of the "
        "relative change of the mean, as the paper computes them (its numbers follow from "
        "its tables this way); 95% bootstrap intervals over seeds, leaving out the "
        "resamples in which a pair's base mean is 0 (counted where there are any). Each "
        "pair's own change is listed below: a base near 0 makes one pair's change large "
        "enough to carry the average. The training share counts dangerous robot-steps from "
        "the start of learning.",
        "",
        "| figure | ours | paper |",
        "|---|---|---|",
    ]
    names = {
        "danger_reduction_vs_plain": "danger reduction, CCR vs plain",
        "danger_reduction_vs_pessimistic": "danger reduction, CCR vs pessimistic",
        "success_change_vs_pessimistic": "success change, CCR vs pessimistic",
        "success_change_vs_plain_turbulence": "success change, CCR vs plain (turbulence)",
        "training_danger_share_maddpg_hidden_obstacle":
            "training dangerous steps since learning started, MADDPG+CCR / MADDPG "
            "(hidden obstacle)",
    }
    for key, label in names.items():
        value = h[key]
        ours = _interval(value)
        notes = []
        if value.get("left_out"):
            notes.append(f"{value['left_out']} pair(s) with a zero base left out")
        if value.get("resamples_dropped"):
            notes.append(f"{value['resamples_dropped']} resamples with a zero base left out")
        if notes:
            ours += f" ({'; '.join(notes)})"
        lines.append(f"| {label} | {ours} | {_pct(p[key])} |")
    ratio = result["obstacle_distance_ratio_maddpg"]
    lines += [
        "| average distance to the obstacle's centre, MADDPG+CCR / MADDPG, robot by robot "
        f"in arrival order (hidden obstacle) | {ratio['low']:.2f}x to {ratio['high']:.2f}x "
        f"({', '.join(f'{r:.2f}' for r in ratio['by_rank'])}) | {ratio['paper'][0]:g}x to "
        f"{ratio['paper'][1]:g}x |",
        "",
        "Each pair's relative change:",
        "",
        "| pair | " + " | ".join(names[key] for key in HEADLINES) + " |",
        "|---|" + "---|" * len(HEADLINES),
    ]
    by_pair: dict[str, dict[str, float | None]] = {}
    for key in HEADLINES:
        for name, change in zip(h[key]["pair_names"], h[key]["per_pair"], strict=True):
            by_pair.setdefault(name, {})[key] = change
    for name, changes in by_pair.items():
        lines.append(f"| {name} | " + " | ".join(
            (_pct(changes[key]) if changes[key] is not None else "zero base")
            if key in changes else "" for key in HEADLINES) + " |")
    c = result["claims"]
    lines += [
        "",
        "### Scorecard: do the paper's claims hold here?",
        "",
        f"* CCR's danger below plain's in {c['danger_lower_vs_plain']['cells']} of 9 cells "
        f"({c['danger_lower_vs_plain']['significant']} significantly, "
        f"{c['danger_lower_vs_plain']['significant_holm']} after Holm's correction over the "
        "9); the paper: 8 of 9.",
        f"* below pessimistic's in {c['danger_lower_vs_pessimistic']['cells']} of 9 "
        f"({c['danger_lower_vs_pessimistic']['significant']} significantly, "
        f"{c['danger_lower_vs_pessimistic']['significant_holm']} after Holm); the paper: 9 "
        "of 9.",
        f"* hidden-obstacle success above both baselines for "
        f"{c['hidden_obstacle_success_above_both']['learners']} of 3 learners "
        f"({c['hidden_obstacle_success_above_both']['significant']} significantly); the "
        "paper: 3 of 3.",
        "",
    ]
    return "\n".join(lines)


def plateau_table(plain_records: list[dict]) -> list[str]:
    """The plain learners' plateau checks with their sizes: the mean return of the last
    20% of evaluations, that of the 20% before with its 95% interval, and the change, so
    a reader sees whether a curve that failed the test rose by a hair or was still
    learning."""
    lines = ["| plain learner | return, last 20% | return, 20% before [95% CI] | change | "
             "levelled off |", "|---|---|---|---|---|"]
    for r in plain_records:
        check = r["return_plateau"]
        name = f"{SCENARIO_NAMES[r['scenario']]}, {LEARNER_NAMES[r['algo']]}"
        if "last" not in check:
            lines.append(f"| {name} | | | | undetermined: {check.get('why', '')} |")
            continue
        change = check["last"] - check["previous"]
        relative = (f" ({100 * change / abs(check['previous']):+.1f}%)"
                    if check["previous"] != 0 else "")
        verdict = {True: "yes", False: "**no**", None: "undetermined"}[check["plateaued"]]
        lines.append(
            f"| {name} | {check['last']:.2f} | {check['previous']:.2f} "
            f"[{check['ci_low']:.2f}, {check['ci_high']:.2f}] | {change:+.2f}{relative} "
            f"| {verdict} |")
    return lines + [""]


def _convergence_text(not_levelled: list[dict], undetermined: list[dict]) -> str:
    def names(records: list[dict]) -> str:
        return ", ".join(f"{r['scenario']} {LEARNER_NAMES[r['algo']]}" for r in records)

    if not not_levelled and not undetermined:
        return "It did in every cell."
    text = f"It did **not** in: {names(not_levelled)}." if not_levelled else ""
    if undetermined:
        text += (" " if text else "") + ("Undetermined (too few evaluations or seeds, or a "
                                         f"NaN return) in: {names(undetermined)}.")
    return text


def _probability(value: dict) -> str:
    return (f"{value['probability']:.2f} [{value['ci_low']:.2f}, {value['ci_high']:.2f}]")


# ---------------------------------------------------------------------------- figures
def draw_figures(cells, out: Path, quick: bool = False) -> list[Path]:
    """The tables' figures from the cells (``quick``: every title says the quick mode)."""
    note = protocol.QUICK_FIGURE if quick else ""
    written = []
    for scenario in PAPER_SCENARIOS:
        panels = {}
        for algo in ALGOS:
            panels[LEARNER_NAMES[algo]] = {
                variant: (np.asarray(cells[(scenario, algo, variant)]["history"]["return"]),
                          np.asarray(cells[(scenario, algo, variant)]["history"]
                                     ["danger_frequency"]))
                for variant in VARIANTS}
        path = out / f"progress_{scenario}.png"
        draw_progress_matched(panels, path, title=f"{note}{SCENARIO_NAMES[scenario]}: dangerous-"
                              "behaviour frequency against return along training")
        written.append(path)
    metrics = ("return", "danger_frequency", "success_rate", "learning_danger_steps")
    for scenario in PAPER_SCENARIOS:
        for algo in ALGOS:
            curves = Curves()
            for variant in VARIANTS:
                cell = cells[(scenario, algo, variant)]
                steps = np.asarray(cell["history"]["env_steps"][0])
                curves.add(LEARNER_NAMES[algo] + VARIANT_SUFFIX[variant], steps,
                           {m: np.asarray(cell["history"][m]) for m in metrics},
                           colour=VARIANT_COLOURS[variant])  # as in the progress figures
            path = out / f"curves_{scenario}_{algo}.png"
            draw_curves(curves, path, metrics=metrics,
                        title=f"{note}{SCENARIO_NAMES[scenario]}, {LEARNER_NAMES[algo]}: plain, "
                        "pessimistic and CCR during training")
            written.append(path)
    plain = cells[("hidden_obstacle", "maddpg", "plain")]
    ccr = cells[("hidden_obstacle", "maddpg", "ccr")]
    path = out / "trajectories_hidden_obstacle_maddpg.png"
    draw_trajectories(plain, ccr, path, note)
    written.append(path)
    path = out / "distance_hidden_obstacle_maddpg.png"
    draw_obstacle_distances(np.asarray(plain["arrival"]["centre_distance"]),
                            np.asarray(ccr["arrival"]["centre_distance"]), path, note)
    written.append(path)
    return written


def _record(cell: dict) -> EpisodeRecord:
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
        danger=np.concatenate([np.zeros((1, positions.shape[1]), bool),
                               np.asarray(episode["danger"], bool)]),
        caption=f"seed {cell['seeds'][0]}, the first recorded evaluation episode",
    )


def draw_trajectories(plain: dict, ccr: dict, path: Path, note: str = "") -> None:
    """The same evaluation episode (same starts, same obstacle) by both teams, side by side
    (``note`` before each label)."""
    images = []
    with tempfile.TemporaryDirectory() as folder:
        for name, cell in (("plain", plain), ("ccr", ccr)):
            file = Path(folder) / f"{name}.png"
            draw_episode(_record(cell), file, dpi=90)
            images.append(Image.open(file).convert("RGB"))
        width = sum(image.width for image in images)
        height = max(image.height for image in images)
        canvas = Image.new("RGB", (width, height + 40), "white")
        draw = ImageDraw.Draw(canvas)
        font = ImageFont.load_default(size=22)
        x = 0
        for image, label in zip(images, ("MADDPG (CCR not running: all standby)",
                                         "MADDPG+CCR (CCR's colours)"), strict=True):
            canvas.paste(image, (x, 40))
            draw.text((x + 20, 8), note + label, fill="black", font=font)
            x += image.width
        with replacing(path) as temporary:
            canvas.save(temporary)


# ---------------------------------------------------------------------------- command
def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0],
                        epilog=__doc__.split("\n\n")[3],
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=None,
                        help=f"seeds per cell, at least 2 (default: {len(protocol.TABLE_SEEDS)})")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=None,
                        help="first seed (default: 0); must stay clear of the selection "
                        "seeds 100-102 and the budgets' 200-202")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run (default: the protocol's budgets, "
                        f"{protocol.budgets_text()})")
    parser.add_argument("--lam", type=cli.non_negative_float, default=None,
                        help="CCR's lambda (default: the lambda search's choice, "
                        "<searches>/ccr/search.json)")
    parser.add_argument("--penalty", type=cli.non_negative_float, default=None,
                        help="the pessimistic penalty (default: the penalty search's choice, "
                        "<searches>/pessimistic/search.json)")
    parser.add_argument("--searches", type=Path, default=None,
                        help="the folder holding both searches' results, ccr/ and "
                        "pessimistic/, whose choices the tables use (default: the committed "
                        "ones, experiments/results/search; `make sweep` and `make "
                        "penalty-sweep` write runs/search; with --quick the default is "
                        "lambda 30 and penalty 1, and a named folder gives its quick "
                        "searches' provisional choices)")
    parser.add_argument("--scenarios", nargs="+", choices=PAPER_SCENARIOS,
                        default=list(PAPER_SCENARIOS),
                        help="train only these scenarios' programs (default: all three; the "
                        "tables are written once all 18 programs exist)")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS),
                        help="train only these learners' programs (default: all three)")
    parser.add_argument("--quick", action="store_true",
                        help=protocol.quick_help())
    add_out_options(parser, "tables", default_text="runs/tables")
    parser.add_argument("--part-seeds", type=cli.seed_int, nargs="+", default=None,
                        help="train only these of the seeds, as a part of each program kept in "
                        "<out>/parts/ and joined into its cells once parts cover all their "
                        "seeds (for a machine that cannot train a whole program at one sitting)")
    add_checkpoint_option(parser)
    add_no_train_option(parser)
    return parser


def selected(variant: str, given: float | None, quick: bool, searches: Path | None = None,
             steps: int | None = None) -> tuple[float, str]:
    """The value of ``variant``'s parameter and where it came from: given, or the
    search's result in ``searches/<variant>/`` (default :data:`SEARCHES`), the protocol's
    choice only, made at the budgets these tables train (``steps`` per run, else the
    protocol's); with ``quick``, a fixed value unless ``searches`` names (quick) searches,
    whose provisional choice it then takes, to check the way from searches to tables."""
    if given is not None:
        return given, "given on the command line"
    if quick and searches is None:
        return {"ccr": 30.0, "pessimistic": 1.0}[variant], "the quick mode's fixed value"
    searches = SEARCHES if searches is None else searches
    path = searches / variant / "search.json"
    search = read_json(path)
    if not search or "selection" not in search:
        option = "--lam" if variant == "ccr" else "--penalty"
        raise cli.UsageError(f"no {variant} search result at {path}: run experiments/search.py "
                             f"--variant {variant} first, name its folder's parent with "
                             f"--searches, or give {option}")
    chosen = search["selection"]
    if quick:
        return float(chosen["value"]), f"the provisional choice of the search in {path.parent}"
    if not chosen.get("protocol"):
        option = "--lam" if variant == "ccr" else "--penalty"
        why = chosen.get("provisional_because") or "made before selections said so"
        raise cli.UsageError(f"the {variant} search at {path} is not the protocol's choice "
                             f"({why}): finish it on all 9 pairs at the protocol's settings, "
                             f"or give {option}")
    budgets = {algo: protocol.budget(algo, steps) for algo in ALGOS}
    if search.get("budgets") != budgets:  # e.g. the protocol's budgets changed after it ran
        raise cli.UsageError(f"the {variant} search at {path} trained the budgets "
                             f"{search.get('budgets')}, not these tables' {budgets}: run it "
                             "again at these budgets, or name searches made at them with "
                             "--searches")
    where = path.parent.name if searches == SEARCHES else str(path.parent)
    fallback = " (its fallback: no value met the rule)" if chosen.get("fallback") else ""
    return float(chosen["value"]), f"selected by the search in {where}{fallback}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out = args.out or Path("runs/tables")
    sources: dict[str, str] = {}

    def settings_of() -> Settings:
        check_quick_out(args.quick, args.out)
        fields: dict[str, Any] = dict(QUICK, quick=True) if args.quick else {}
        if args.steps is not None:
            fields["steps"] = args.steps
        offset = args.seed_offset if args.seed_offset is not None else fields.get(
            "seeds", protocol.TABLE_SEEDS)[0]
        count = args.seeds or len(fields.get("seeds", protocol.TABLE_SEEDS))
        fields["seeds"] = tuple(range(offset, offset + count))
        problem = protocol.seed_overlap(fields["seeds"], offset,
                                        ("the selection", "the budgets'"))
        if problem:
            raise cli.UsageError(problem)
        fields["part_seeds"] = part_seeds_from(args.part_seeds, fields["seeds"], "tables")
        fields["scenarios"] = tuple(dict.fromkeys(args.scenarios))
        fields["algos"] = tuple(dict.fromkeys(args.algos))

        def validated(settings: Settings) -> Settings:
            for job in jobs_of(settings):  # every configuration validated before compiling
                for variant in job.variants:
                    settings.config(job.scenario, job.algo, variant)
            return settings

        # The searches' choices last: the command line's own problems are named first.
        settings = validated(Settings(lam=0.0, penalty=0.0, **fields))
        chosen, problems = {}, []
        for name, variant, given in (("lam", "ccr", args.lam),
                                     ("penalty", "pessimistic", args.penalty)):
            try:  # both named at once when both are missing
                chosen[name], sources[name] = selected(variant, given, args.quick,
                                                       args.searches, args.steps)
            except cli.UsageError as error:
                problems.append(str(error))
        if problems:
            raise cli.UsageError("; and ".join(problems))
        settings = validated(dataclasses.replace(settings, **chosen))
        if args.no_train:
            cells = [(job.scenario, job.algo, variant) for job in jobs_of(settings)
                     for variant in job.variants]
            refuse_untrained({cell_stem(*cell): variant_cell_path(out, *cell) for cell in cells},
                             settings_record(settings), out,
                             "--part-seeds" if settings.part_seeds else "")
        return settings

    settings, ledger = open_experiment(PROG, argv, out, args.force, settings_of)
    trained = run_grid(settings, out, ledger, Partial(out, args.checkpoint_minutes))
    ledger.record(trained, finished=True)
    cells, missing = grid_cells(out, settings)
    if missing:
        total = len(grid_jobs())
        print(f"{total - len(missing)} of {total} programs made in {out}; the tables need them all "
              f"(missing: {', '.join(missing)}): run again naming the others, or all")
        return 0
    controllers = reference_rows(settings)
    whole = dataclasses.replace(settings, scenarios=PAPER_SCENARIOS, algos=ALGOS)  # all 18 exist
    result = summary(cells, whole, ledger.invocations, controllers, sources)
    write_atomic(out / "tables.json", json.dumps(result, indent=1) + "\n")
    write_atomic(out / "tables.md", tables_markdown(result))
    figures = draw_figures(cells, out, settings.quick)
    print(tables_markdown(result))
    print(f"wrote {out / 'tables.md'}, {out / 'tables.json'} and "
          + ", ".join(str(f) for f in figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, STOPPED_KEPT))
