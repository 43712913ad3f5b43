"""The tables' grid: what each of its 18 programs trains, the cells it writes, and the
reference controllers' rows.

Per scenario and learner, two programs: plain and pessimistic together (plain is the
pessimistic transform with penalty 0, exactly), and CCR; each trains all its runs at once,
sharded over every device (:mod:`ccrjax.training.grid`); while one program trains, the next
one compiles. Every finished cell (scenario, learner, variant) is written atomically to
``<out>/cells/<scenario>-<algo>-<variant>.json``: per-seed final evaluations and curves,
whether the return plateaued, the first non-finite iteration per seed, the behaviour
measurements, the program's times, device and commit.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

from ccrjax.run import distributed
from ccrjax.run.folder import (
    POINT_METRICS,
    git_commit,
    write_atomic,
)
from ccrjax.run.stats import plateau_or_undetermined
from ccrjax.training import ALGOS, TrainConfig, make_env
from ccrjax.training.grid import GridRuns, GridTraining
from ccrjax.transforms import Pessimistic
from ccrjax.transforms.ccr import CCR, CCRConfig
from ccrjax.viz.analysis import arrival_analysis, followers_closest
from experiments import protocol
from experiments.cell_identity import cell_is_current, settings_record, training_record
from experiments.ledger import (
    Ledger,
    Partial,
    ProgramProgress,
    device_name,
    log,
    read_json,
)
from experiments.paper import PAPER_SCENARIOS
from experiments.reference_controllers import evaluate_controller

VARIANTS = ("plain", "pessimistic", "ccr")
LEARNER_NAMES = protocol.LEARNER_NAMES
VARIANT_SUFFIX = {"plain": "", "pessimistic": " (Pessimistic)", "ccr": "+CCR"}
SCENARIO_NAMES = {"hidden_obstacle": "hidden obstacle", "turbulence": "turbulence",
                  "strong_wind": "strong wind"}
CONTROLLERS = {"go_to_goal": "go-to-goal (reference)", "oracle": "oracle (reference)"}
METRICS = POINT_METRICS


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

    def run_params(self, variant: str) -> dict[str, float]:
        """The run parameters a program of ``variant`` alone trains every seed with."""
        return {"ccr": {"lam": self.lam}, "pessimistic": {"penalty": self.penalty}}[variant]


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
    (variant,) = job.variants
    config = settings.config(job.scenario, job.algo, variant)
    params = {name: [value] * len(seeds) for name, value in settings.run_params(variant).items()}
    return GridTraining(config, seeds, params, record_episodes=episodes, record_key=key)


def cells_of(job: Job, runs: GridRuns, settings: Settings,
             measure: Callable[[dict[str, np.ndarray]], dict] | None = None
             ) -> dict[str, dict]:
    """The finished cells of a job's runs, by variant; ``measure`` (of a variant's recorded
    episodes, leading seed axis) adds what an experiment measures beyond the tables, as
    the cell's ``measures``."""
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
            # The metrics' curves, and the transform's own (a Lagrange multiplier's path).
            "history": {m: part.history[m].tolist() for m in part.history},
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
        if measure is not None:
            cell["measures"] = measure(episodes)
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


def grid_jobs(algos: tuple[str, ...] = ALGOS) -> list[Job]:
    """The whole grid's programs for the learner family ``algos``: two per scenario and
    learner (18 for the paper's three learners, 12 for the on-policy two)."""
    return [Job(scenario, algo, variants) for scenario in PAPER_SCENARIOS for algo in algos
            for variants in (("plain", "pessimistic"), ("ccr",))]


def jobs_of(settings: Settings, variants: tuple[str, ...] = VARIANTS) -> list[Job]:
    """The programs this invocation trains: ``settings.scenarios`` x ``settings.algos``,
    those holding ``variants``. Plain trains in one program with pessimistic (penalty 0
    beside the penalty); pessimistic without plain is a program of its runs alone, of the
    same configurations and seeds."""
    jobs = []
    for job in grid_jobs(protocol.family(settings.algos)):
        if job.scenario not in settings.scenarios or job.algo not in settings.algos:
            continue
        if "plain" in job.variants and "plain" not in variants:
            if "pessimistic" in variants:
                jobs.append(Job(job.scenario, job.algo, ("pessimistic",)))
        elif set(job.variants) & set(variants):
            jobs.append(job)
    return jobs


def job_cells(out: Path, job: Job, settings: Settings) -> dict[str, dict] | None:
    """A program's cells in ``out`` by variant, if all were made with ``settings``."""
    found = [read_cell(variant_cell_path(out, job.scenario, job.algo, v), settings)
             for v in job.variants]
    return dict(zip(job.variants, found, strict=True)) if all(found) else None


def grid_cells(out: Path, settings: Settings) -> tuple[dict, list[str]]:
    """Every cell of the whole grid of ``settings``' learner family found in ``out`` by
    (scenario, algo, variant), and the names of the programs still missing."""
    cells, missing = {}, []
    for job in grid_jobs(protocol.family(settings.algos)):
        found = job_cells(out, job, settings)
        if found is None:
            missing.append(job.name)
        else:
            cells.update({(job.scenario, job.algo, v): c for v, c in found.items()})
    return cells, missing


def cell_stem(scenario: str, algo: str, variant: str) -> str:
    """A cell's name: its file in ``cells/``."""
    return f"{scenario}-{algo}-{variant}"


def run_grid(settings: Settings, out: Path, ledger: Ledger, partial: Partial,
             jobs: list[Job] | None = None,
             measure: Callable[[dict[str, np.ndarray]], dict] | None = None,
             trained_before: int = 0) -> int:
    """Trains every missing program of ``settings`` (``jobs``: those programs, default the
    tables' :func:`jobs_of`; ``measure``: :func:`cells_of`'s), compiling the next program
    while one trains; returns the number of programs trained. ``ledger`` records, as each
    program finishes, the invocation's programs so far: ``trained_before`` (those of its
    earlier calls, where one invocation calls this once per group of programs) and this
    call's. With several processes
    (:mod:`ccrjax.run.distributed`) each trains its share of every program's runs and
    process 0 writes the cells."""
    jobs = jobs_of(settings) if jobs is None else jobs
    # Several processes train the same programs in the same order: process 0's list.
    todo = [job for job in jobs if distributed.agree(job_cells(out, job, settings) is None)]
    seeds = settings.seeds
    budgets = f"budgets { {a: settings.budget(a) for a in settings.algos} }, on {device_name()}"
    log(f"{len(jobs) - len(todo)} of {len(jobs)} programs already done; {len(todo)} to "
        f"train ({len(seeds)} seeds per cell, {budgets})")
    progress = ProgramProgress([(job.name, job.algo,
                          len(job.variants) * len(seeds) * settings.budget(job.algo))
                         for job in todo])
    if distributed.is_primary():
        (out / "cells").mkdir(parents=True, exist_ok=True)
    # Compilation runs ahead in worker threads (XLA's compiler releases the GIL) while the
    # main thread trains; the quick mode's programs run for moments, so there it compiles
    # on both cores at XLA's lowest optimisation level.
    workers = 2 if settings.quick else 1
    with ThreadPoolExecutor(max_workers=workers) as compiler:
        for job in todo:
            job.training = build_training(job, settings)
        compiled = [compiler.submit(job.training.compile, not settings.quick) for job in todo]
        for number, (job, done) in enumerate(zip(todo, compiled, strict=True)):
            done.result()
            runs = partial.train(job.training, job.name)
            if distributed.is_primary():
                for variant, cell in cells_of(job, runs, settings, measure).items():
                    write_atomic(variant_cell_path(out, job.scenario, job.algo, variant),
                                 json.dumps(cell) + "\n")
            partial.discard(job.name)
            job.training = None  # free the compiled program
            ledger.record(trained_before + number + 1)
            log(progress.finished(number, runs.run_s + runs.compile_s))
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

