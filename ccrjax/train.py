"""``python -m ccrjax.train``: train a team of robots and leave a run folder behind.

::

    python -m ccrjax.train --scenario hidden_obstacle --algo maddpg --variant ccr --seeds 3
    python -m ccrjax.train --out runs/my-run --resume        # continue a stopped run
    python -m ccrjax.evaluate runs/my-run                    # fresh episodes of the result

All ``--seeds`` seeds train at once in one compiled program (``jax.vmap`` over the
training program of :mod:`ccrjax.training.program`). Python drives the outside: it runs
the program one chunk at a time (``--eval-every`` environment steps, then an
evaluation), writes each evaluation to ``metrics.csv`` and TensorBoard, saves
checkpoints, and draws the pictures at the end (:mod:`ccrjax.run.folder` lists
the folder's files).

A run stopped at any moment (Ctrl-C, SIGTERM, even SIGKILL) and resumed with
``--resume`` ends with exactly the same parameters and metrics as the same run
never interrupted: the whole state, random keys included, is in the checkpoint,
and the same compiled chunk runs from it. Ctrl-C and SIGTERM are honoured at the next
safe point (after compilation, or after the current chunk, which saves a checkpoint) and
exit with status 130 saying what was kept; a run stopped before its first checkpoint starts
again in the same folder. Mistakes on the command line get one line and exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.util
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from ccrjax import cli
from ccrjax.agents import ALGOS
from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.agents.maac import MAACConfig
from ccrjax.agents.replay import grow
from ccrjax.cli import INTERRUPTED, UsageError
from ccrjax.envs.scenarios import SCENARIOS, Layout
from ccrjax.run.checkpoint import CheckpointError, Checkpoints, holds_buffer, report_skipped
from ccrjax.run.folder import (
    EVAL_METRICS,
    POINT_METRICS,
    TRAINING_COUNTS,
    RunFolder,
    environment_record,
    fingerprint,
    folder_bytes,
    summary_table,
    timestamp,
)
from ccrjax.run.policy import POLICY_DIR, POLICY_RECORD, export_policy
from ccrjax.run.spec import RunSpec
from ccrjax.training import DEFAULT_BUDGET, TrainConfig, make_train
from ccrjax.training.config import TRANSFORM_TYPES
from ccrjax.training.program import NonFinite, first_nonfinite
from ccrjax.transforms import VARIANTS, Pessimistic
from ccrjax.transforms.ccr import CCR, CCRConfig, DangerFlags
from ccrjax.viz.episode_pictures import (
    PICTURE_KEY,
    record_trained_episode,
    seed_slice,
    unbroken,
    write_episode_pictures,
)
from ccrjax.viz.plots import Curves, curves_from_rows, draw_curves

PROG = "python -m ccrjax.train"
# The configuration dataclasses whose fields are options, and the options' prefix
# (--ddpg-gamma is DDPGConfig.gamma): errors name the option, not the field.
# DangerFlags' comm_range is --ccr-comm-range too.
OPTION_PREFIXES = {"DDPGConfig": "ddpg", "MAACConfig": "maac", "CCRConfig": "ccr",
                   "DangerFlags": "ccr",
                   "Layout": "layout"}
# The layout's fields that are options: the regime's two knobs (hazard placement, team
# formation) and the arena that a long column needs; the start box and target area stay.
LAYOUT_OPTION_FIELDS = ("hazard_x_range", "hazard_y_range", "formation", "column_spacing",
                        "column_lateral", "arena_half_extent")
# CCRConfig's fields of the dynamics model: no option of the variants without one.
CCR_MODEL_FIELDS = ("degree", "ridge", "tolerance")
# A new run's defaults are make train's: MADDPG with CCR on the hidden obstacle.
DEFAULT_TRAIN = TrainConfig(scenario="hidden_obstacle", variant="ccr")
# The options that set a TrainConfig field (option, field, converter, extras): the parser
# and resolve() both read this table; the option's value lands in args.<field>.
TRAIN_OPTIONS: tuple[tuple[str, str, Any, dict[str, Any]], ...] = (
    ("--scenario", "scenario", None, {"choices": SCENARIOS}),
    ("--algo", "algo", None, {"choices": ALGOS}),
    ("--variant", "variant", None, {"choices": VARIANTS}),
    ("--steps", "total_env_steps", cli.positive_int,
     {"shown": ", ".join(f"{v:,} for {k}" for k, v in DEFAULT_BUDGET.items())}),
    ("--num-envs", "num_envs", cli.int_in(1, 65536), {}),
    ("--robots", "num_robots", cli.int_in(2, 64), {}),
    ("--episode-length", "episode_length", cli.int_in(1, 10_000), {}),
    ("--eval-every", "eval_every", cli.positive_int, {}),
    ("--eval-episodes", "eval_episodes", cli.int_in(1, 65536), {}),
    ("--learning-starts", "learning_starts", cli.non_negative_int, {}),
)
# The options that set a RunSpec field: the seeds (with the run's), then the checkpoints.
SPEC_OPTIONS: tuple[tuple[str, str, Any], ...] = (
    ("--seeds", "seeds", cli.int_in(1, 1024)),
    ("--seed-offset", "seed_offset", cli.seed_int),
    ("--checkpoint-every", "checkpoint_every", cli.positive_int),
    ("--keep-checkpoints", "keep_checkpoints", cli.int_in(1, 1000)),
)
NONFINITE = 1


# ---------------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:

    parser = cli.Parser(
        prog=PROG,
        description="Train a robot team (IDDPG, MADDPG or MAAC; plain, pessimistic or CCR) "
        "on one emergency scenario, all seeds at once, into a run folder.",
        epilog="Every option left out keeps its default; with --resume, the run's own "
        "configuration (config.json) is used and options that contradict it are refused.",
    )
    # Every option's help and default come from the dataclass field it sets.
    run = parser.add_argument_group("the run")
    for option, field, convert, extra in TRAIN_OPTIONS:
        cli.add_field_option(run, option, DEFAULT_TRAIN, field, convert, **extra)
    for option, owner, field in (("--lam", CCRConfig(), "lam"),
                                 ("--penalty", Pessimistic(), "penalty")):
        cli.add_field_option(run, option, owner, field, cli.non_negative_float)
    spec = RunSpec(train=DEFAULT_TRAIN)
    for option, field, convert in SPEC_OPTIONS[:2]:
        cli.add_field_option(run, option, spec, field, convert)

    folder = parser.add_argument_group("the run folder")
    folder.add_argument("--out", type=Path, default=None,
                        help="run folder (default: runs/<scenario>-<algo>-<variant>-<time>)")
    folder.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its latest checkpoint")
    for option, field, convert in SPEC_OPTIONS[2:]:
        cli.add_field_option(folder, option, spec, field, convert)
    folder.add_argument("--keep-buffer", action="store_true",
                        help="keep the replay buffer in a finished run's last checkpoint (it "
                        "is dropped by default: only extending the run exactly needs it)")
    folder.add_argument("--no-progress", action="store_true",
                        help="one line per evaluation instead of a progress bar")
    folder.add_argument("--compilation-cache", default=cli.default_cache_dir(), metavar="DIR",
                        help="where compiled programs are kept, so that a resumed or repeated "
                        "run starts in seconds (default: %(default)s)")
    folder.add_argument("--no-compilation-cache", action="store_true",
                        help="compile from scratch and keep nothing")

    cli.add_dataclass_options(parser, DDPGConfig, OPTION_PREFIXES["DDPGConfig"],
                              "IDDPG / MADDPG hyperparameters",
                              exclude=("centralised_critic",))
    cli.add_dataclass_options(parser, MAACConfig, OPTION_PREFIXES["MAACConfig"],
                              "MAAC hyperparameters")
    cli.add_dataclass_options(parser, CCRConfig, OPTION_PREFIXES["CCRConfig"],
                              "CCR parameters (ccr and its parts ccr_scores, ccr_reward, "
                              "ccr_perfect; --ccr-comm-range also danger_flags)",
                              exclude=("lam",))
    cli.add_dataclass_options(
        parser, Layout, OPTION_PREFIXES["Layout"],
        "regime: hazard placement and team formation (a value starting with '-' is written "
        "--layout-hazard-y-range=-1,1)",
        exclude=[f.name for f in dataclasses.fields(Layout) if f.name not in LAYOUT_OPTION_FIELDS])
    return parser


def ccr_option_variants(field: str) -> list[str]:
    """The variants that take ``CCRConfig``'s ``field`` (``--lam``, ``--ccr-*``): CCR and its
    parts (:mod:`ccrjax.transforms.ccr.parts`), ``lam`` only where the intrinsic reward is
    added, the model's ``degree``, ``ridge`` and ``tolerance`` only where the model detects;
    ``comm_range`` also for ``danger_flags``."""
    variants = []
    for variant, transform_type in TRANSFORM_TYPES.items():
        if issubclass(transform_type, CCR):
            if (field != "lam" or transform_type.intrinsic) and (
                    field not in CCR_MODEL_FIELDS or transform_type.detector == "model"):
                variants.append(variant)
        elif issubclass(transform_type, DangerFlags) and field == "comm_range":
            variants.append(variant)
    return variants


def resolve(args: argparse.Namespace, base: RunSpec | None) -> RunSpec:
    """The run the command line asks for: ``base`` (a resumed run's, or the defaults) with
    every option given on top, every value the run uses written out (the learner's and the
    transform's parameters, the budget) so that ``config.json`` shows them. Raises
    ``ValueError`` for values the configuration refuses."""

    train = base.train if base is not None else DEFAULT_TRAIN
    fields = {field: getattr(args, field) for _, field, _, _ in TRAIN_OPTIONS
              if getattr(args, field) is not None}
    algo = fields.get("algo", train.algo)
    variant = fields.get("variant", train.variant)
    if algo != train.algo:  # another learner: its own defaults and budget
        fields["learner"] = None
        fields.setdefault("total_env_steps", None)
    if variant != train.variant:
        fields["transform"] = None

    ddpg, maac = cli.dataclass_overrides(args, "ddpg"), cli.dataclass_overrides(args, "maac")
    if ddpg and algo == "maac":
        raise UsageError("--ddpg-* options apply to --algo iddpg and maddpg, not maac")
    if maac and algo != "maac":
        raise UsageError(f"--maac-* options apply to --algo maac, not {algo}")
    if args.penalty is not None and variant != "pessimistic":
        raise UsageError(f"--penalty applies to --variant pessimistic, not {variant}")
    ccr = cli.dataclass_overrides(args, "ccr")
    if args.lam is not None:
        ccr["lam"] = args.lam
    for field in ccr:  # each --ccr-* option (and --lam) only where the variant uses it
        allowed = ccr_option_variants(field)
        if variant not in allowed:
            option = "--lam" if field == "lam" else f"--ccr-{field.replace('_', '-')}"
            listed = " or ".join([", ".join(allowed[:-1]), allowed[-1]] if len(allowed) > 1
                                 else allowed)
            raise UsageError(f"{option} applies to --variant {listed}, not {variant}")
    layout = cli.dataclass_overrides(args, "layout")
    if layout:
        fields["layout_params"] = {**train.layout_params, **layout}
    train = dataclasses.replace(train, **fields)
    if ddpg or maac:
        train = dataclasses.replace(train, learner=dataclasses.replace(
            train.learner_config, **(ddpg or maac)))
    if args.penalty is not None:
        train = dataclasses.replace(train, transform=Pessimistic(penalty=args.penalty))
    if ccr:
        transform = train.transform_config  # CCR or one of its parts, or DangerFlags
        transform = (type(transform)(dataclasses.replace(transform.config, **ccr))
                     if isinstance(transform, CCR) else dataclasses.replace(transform, **ccr))
        train = dataclasses.replace(train, transform=transform)
    train = dataclasses.replace(train, learner=train.learner_config,
                                transform=train.transform_config,
                                total_env_steps=train.budget)

    run_fields = {field: getattr(args, field) for _, field, _ in SPEC_OPTIONS
                  if getattr(args, field) is not None}
    if base is None:
        return RunSpec(train=train, **run_fields)
    return dataclasses.replace(base, train=train, **run_fields)


def differences(saved: dict[str, Any], asked: dict[str, Any], prefix: str = "") -> list[str]:
    """``name: saved -> asked`` for every entry that differs (nested dicts flattened)."""
    lines = []
    for key in sorted(set(saved) | set(asked)):
        a, b = saved.get(key), asked.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            lines += differences(a, b, f"{prefix}{key}.")
        elif a != b:
            lines.append(f"{prefix}{key} is {a!r} in the run, {b!r} here")
    return lines


# ---------------------------------------------------------------------------- the folder
def check_writable(path: Path) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as error:
        reason = error.strerror or str(error)
        raise UsageError(f"cannot write to the run folder {path}: {reason}") from None


def open_folder(args: argparse.Namespace) -> tuple[Any, RunSpec, dict | None]:
    """Checks the run folder against the command and returns it, the run, and (resuming)
    the saved configuration record."""

    if args.resume and args.out is None:
        raise UsageError("--resume needs --out: the folder of the run to continue")
    if args.out is None:
        spec = resolve(args, None)
        name = f"{spec.train.scenario}-{spec.train.algo}-{spec.train.variant}-{timestamp()}"
        args.out = Path("runs") / name
    folder = RunFolder(args.out)
    if args.resume:
        if not folder.holds_run():
            raise UsageError(f"--resume: {folder.path} holds no run (no config.json)")
        try:
            record = folder.read_config()
            saved = RunSpec.from_dict(record["run"])
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise UsageError(f"--resume: cannot read {folder.config_path}: {error}") from None
        spec = resolve(args, saved)
        asked, budget = spec.train.total_env_steps, saved.train.total_env_steps
        if asked < budget:
            raise UsageError(f"--resume --steps {asked:,}: the run's budget is {budget:,} "
                             "environment steps per seed; a run can be extended, not shortened")
        same_budget = dataclasses.replace(spec, train=dataclasses.replace(
            spec.train, total_env_steps=budget))
        changed = differences(saved.to_dict(), same_budget.to_dict())
        if changed:
            raise UsageError(
                f"--resume: options contradict the run in {folder.path} ("
                + "; ".join(changed) + "); a run resumes with its own configuration "
                "(only --steps may grow, to extend it)"
            )
        check_writable(folder.path)
        if asked > budget:  # the extension is recorded where the run is described
            steps = folder.checkpoint_steps()
            exact = bool(steps) and holds_buffer(folder.checkpoint_dir, steps[-1])
            record.setdefault("extensions", []).append(
                {"from_total_env_steps": budget, "to_total_env_steps": asked,
                 "runs_as_total_env_steps": spec.train.total_env_steps_run,
                 "replay_buffer": "in the last checkpoint: the extension is exact" if exact
                 else "none in the last checkpoint: training goes on from an empty buffer",
                 "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
            record["schedule"] = spec.train.schedule()
        return folder, spec, record
    spec = resolve(args, None)
    if folder.holds_run() and folder.has_checkpoint():
        raise UsageError(
            f"{folder.path} already holds a run; pass --resume to continue it, "
            "or choose another --out (nothing was overwritten)"
        )
    if folder.holds_run():  # nothing of it can be resumed: this run takes its place
        print(f"{folder.path} holds a run stopped before its first checkpoint; this run "
              "starts in its place", file=sys.stderr, flush=True)
        check_writable(folder.path)
        return folder, spec, None
    if folder.path.exists() and (not folder.path.is_dir() or any(folder.path.iterdir())):
        raise UsageError(f"{folder.path} exists and is not an empty folder; choose another --out")
    check_writable(folder.path)
    return folder, spec, None


# ---------------------------------------------------------------------------- progress
class Progress:
    """A progress bar on a terminal, one line per evaluation otherwise."""

    def __init__(self, total_steps: int, seeds: int, done_steps: int, bar: bool) -> None:
        self.seeds = seeds
        self.total = total_steps
        self.bar = None
        self.last_time = time.perf_counter()
        self.last_steps = done_steps
        if bar:

            self.bar = tqdm(total=total_steps, initial=done_steps, unit="step", unit_scale=True,
                            desc=f"training ({seeds} seed{'s' * (seeds > 1)}, steps per seed)",
                            file=sys.stderr, dynamic_ncols=True, smoothing=0.3)

    def update(self, steps: int, success: float, danger: float) -> None:
        now = time.perf_counter()
        rate = (steps - self.last_steps) * self.seeds / max(now - self.last_time, 1e-9)
        self.last_time, self.last_steps = now, steps
        if self.bar is not None:
            self.bar.set_postfix_str(
                f"{rate:,.0f} env steps/s (all seeds), success {success:.2f}, "
                f"danger {danger:.3f}"
            )
            self.bar.update(steps - self.bar.n)
        else:
            print(f"steps {steps:,}/{self.total:,} per seed · {rate:,.0f} env steps/s (all "
                  "seeds) · "
                  f"success {success:.3f} · danger {danger:.3f}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def compile_phase(what: str, function, *examples, ticker: bool):
    """Compiles ``function`` for ``examples`` as its own announced phase; returns it compiled."""
    print(f"compiling {what}; training starts when it is done ...",
          file=sys.stderr, flush=True)
    start = time.perf_counter()
    done = threading.Event()

    def tick() -> None:
        while not done.wait(1.0):
            print(f"\r  compiling ... {time.perf_counter() - start:4.0f} s", end="",
                  file=sys.stderr, flush=True)

    thread = threading.Thread(target=tick, daemon=True) if ticker else None
    if thread:
        thread.start()
    try:
        compiled = function.lower(*examples).compile()
    finally:
        done.set()
        if thread:
            thread.join()
            print("\r", end="", file=sys.stderr)
    print(f"  compiled in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    return compiled


# ---------------------------------------------------------------------------- training
class StopRequest:
    """Turns the first Ctrl-C / SIGTERM into a request the command honours at its next safe
    point: after compilation (XLA cannot be interrupted while it compiles), after the chunk
    in progress (which then saves a checkpoint), or once a finished run's files are written.
    A second request raises ``KeyboardInterrupt`` as soon as Python runs again."""

    WHEN = {
        "preparing": "stopping as soon as the training program is compiled (XLA cannot be "
                     "interrupted while it compiles)",
        "training": "finishing the current chunk, then saving a checkpoint",
        "finishing": "the run has finished; stopping once its pictures and policy are written",
    }

    def __init__(self) -> None:
        self.signal_name: str | None = None
        self.phase = "preparing"
        self._previous: dict[int, Any] = {}

    @property
    def requested(self) -> bool:
        return self.signal_name is not None

    def __enter__(self) -> StopRequest:
        for number in (signal.SIGINT, signal.SIGTERM):
            self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)

    def _handle(self, number: int, frame: Any) -> None:
        if self.signal_name is not None:  # a second request: stop at once
            signal.signal(number, self._previous.get(number, signal.SIG_DFL))
            raise KeyboardInterrupt
        self.signal_name = signal.Signals(number).name
        if self.phase != "done":  # once all is written, :meth:`closing` says so at the exit
            print(f"\n{self.signal_name}: {self.WHEN[self.phase]} (press again to stop at once, "
                  "losing the work since the last checkpoint)", file=sys.stderr, flush=True)

    def closing(self, status: int) -> int:
        """The command's exit status: a request that came after the run's last check (its
        files all written) still ends it with 130, said in one line."""
        if status == 0 and self.requested:
            print(f"stopped by {self.signal_name} after the run finished; everything is written",
                  file=sys.stderr, flush=True)
            return INTERRUPTED
        return status


def point_rows(point: dict, seeds: Sequence[int], wall: float) -> list[dict[str, Any]]:
    """One ``metrics.csv`` row per seed from an evaluation point (leaves ``[seeds]``)."""

    rows = []
    for index, seed in enumerate(seeds):
        row = {"seed": seed, "env_steps": int(point["env_steps"][index]), "wall_time_s": wall}
        for name in POINT_METRICS:  # the counts of robot-steps as the integers they are
            value = point[name][index]
            row[name] = int(value) if name in TRAINING_COUNTS else float(value)
        rows.append(row)
    return rows


def state_bytes(abstract_state: Any) -> int:

    return sum(math.prod(x.shape) * np.dtype(x.dtype).itemsize
               for x in jax.tree_util.tree_leaves(abstract_state))


def physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def training_memory() -> tuple[int, str] | None:
    """The memory the training state must fit in, and what holds it: an accelerator's
    (JAX reports its limit; on a GPU the state lives there), else this machine's."""
    try:
        stats = jax.devices()[0].memory_stats()  # None on the CPU
    except (NotImplementedError, RuntimeError):  # a backend that cannot tell: the host
        stats = None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"the {jax.devices()[0].device_kind}"
    memory = physical_memory()
    return None if memory is None else (memory, "this machine")


@dataclasses.dataclass
class Session:
    """A run ready to train (:func:`prepare`): its folder and checkpoints, the program and
    its compiled chunk, the state of every seed, and the evaluation history so far."""

    folder: RunFolder
    spec: RunSpec
    program: Any
    checkpoints: Checkpoints
    chunk: Any  # jitted (state, train: bool) -> (state, evaluation point, training metrics)
    state: Any
    history: list[dict[str, Any]]
    fingerprint: str
    wall_before: float
    started: float  # time.perf_counter() when this invocation began compiling

    @property
    def seeds(self) -> list[int]:
        return self.spec.seed_list

    @property
    def chunk_steps(self) -> int:
        config = self.spec.train
        return config.iterations_per_eval * config.steps_per_iteration

    @property
    def total_steps(self) -> int:
        return self.program.num_evaluations * self.chunk_steps

    @property
    def steps(self) -> int:
        return int(self.history[-1]["env_steps"])

    @property
    def finished(self) -> bool:
        return self.steps >= self.total_steps

    def wall(self) -> float:
        return self.wall_before + time.perf_counter() - self.started

    def save(self) -> None:
        """Starts writing a checkpoint of the current state and history."""
        meta = {"fingerprint": self.fingerprint, "history": self.history,
                "wall_time_s": self.wall()}
        self.checkpoints.save(self.steps, self.state.replace(buffer=None), self.state.buffer,
                              meta)


def prepare(folder: RunFolder, spec: RunSpec, record: dict | None,
            progress_bar: bool) -> Session:
    """Everything before training: the memory check, the folder's configuration record,
    the restored checkpoint (resuming), the compiled chunk, and a new run's first
    evaluation (the untrained policy)."""
    config = spec.train
    program = make_train(config)
    seeds = spec.seed_list
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in seeds])
    abstract_state = jax.eval_shape(jax.vmap(program.init), keys)
    size = state_bytes(abstract_state)
    available = training_memory()
    if available is not None and 2.2 * size > available[0]:
        memory, holder = available
        raise UsageError(
            f"the training state of {len(seeds)} seed(s) needs {size / 2**30:.1f} GiB (twice "
            f"that while training) but {holder} has {memory / 2**30:.1f} GiB; use fewer "
            "--seeds, or a smaller replay buffer (--ddpg-buffer-size / --maac-buffer-size)"
        )
    run_record = spec.to_dict()
    run_fingerprint = fingerprint(run_record)
    resuming = record is not None
    if resuming and record.get("run") != json.loads(json.dumps(run_record)):  # extended
        record["run"] = run_record
        folder.write_config(record)
    if record is None:  # a new run
        record = {**environment_record(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "command": " ".join([PROG, *sys.argv[1:]]) if sys.argv else PROG,
                  "fingerprint": run_fingerprint, "run": run_record,
                  "schedule": config.schedule()}
        folder.write_config(record)
    for note in config.schedule()["notes"]:  # nothing is rounded silently
        print(f"note: {note}", file=sys.stderr, flush=True)
    if record.get("fingerprint") != run_fingerprint:
        raise UsageError(f"{folder.config_path} does not match the run it describes")
    checkpoints = Checkpoints(folder.checkpoint_dir, keep=spec.keep_checkpoints)
    try:
        return _prepared(folder, spec, program, checkpoints, keys, abstract_state, size,
                         run_fingerprint, resuming, progress_bar)
    except BaseException:  # no writer thread outlives a refused or interrupted start
        checkpoints.close()
        folder.close_tensorboard()
        raise


def _prepared(folder: RunFolder, spec: RunSpec, program: Any, checkpoints: Checkpoints,
              keys: jax.Array, abstract_state: Any, size: int, run_fingerprint: str,
              resuming: bool, progress_bar: bool) -> Session:
    """:func:`prepare` once the checkpoints are open: restore, compile, first evaluation."""
    config, seeds = spec.train, spec.seed_list
    chunk_steps = config.iterations_per_eval * config.steps_per_iteration
    total_steps = program.num_evaluations * chunk_steps
    state, history, wall_before = None, [], 0.0
    if checkpoints.steps():
        state, history, wall_before = restore(folder, checkpoints, program, keys,
                                              abstract_state, run_fingerprint, total_steps)
    elif resuming:
        print(f"{folder.path} has no checkpoint (the run stopped before its first one): "
              "it starts again from the beginning, with its configuration",
              file=sys.stderr, flush=True)
    started = time.perf_counter()  # the run's wall time counts its compilation
    chunk = compile_phase(
        f"the training program for {len(seeds)} seed(s) ({size / 2**20:,.0f} MiB of "
        "training state)",
        jax.jit(jax.vmap(program.chunk, in_axes=(0, None))), abstract_state, True,
        ticker=progress_bar,
    )
    session = Session(folder=folder, spec=spec, program=program, checkpoints=checkpoints,
                      chunk=chunk, state=state, history=history, fingerprint=run_fingerprint,
                      wall_before=wall_before, started=started)
    if state is None:
        state = jax.jit(jax.vmap(program.init))(keys)
        session.state, point, _ = chunk(state, False)  # the untrained policy's evaluation
        session.history = point_rows(jax.device_get(point), seeds, session.wall())
        folder.rewrite_metrics(session.history)
        # A start that stopped before its first checkpoint may have left events behind.
        shutil.rmtree(folder.tensorboard_dir, ignore_errors=True)
        folder.open_tensorboard(seeds, purge_step=None)
        for row in session.history:
            folder.log_scalars(row["seed"], row["env_steps"], _eval_scalars(row))
    else:
        # Events written after the checkpoint by the run that stopped are hidden.
        folder.open_tensorboard(seeds, purge_step=session.steps + 1)
    return session


def restore(folder: RunFolder, checkpoints: Checkpoints, program: Any, keys: jax.Array,
            abstract_state: Any, run_fingerprint: str, total_steps: int
            ) -> tuple[Any, list[dict[str, Any]], float]:
    """The latest readable checkpoint's state (its replay buffer grown for an extended run,
    or an empty one where it kept none, said), history and wall time."""
    try:
        restored = checkpoints.restore_latest(abstract_state.replace(buffer=None),
                                              abstract_state.buffer, run_fingerprint)
    except CheckpointError as error:  # IncompatibleCheckpoint included
        raise UsageError(f"--resume: {error}") from None
    report_skipped(restored)
    buffer = restored.buffer
    capacity = abstract_state.buffer.reward.shape[1]
    if buffer is not None and buffer.reward.shape[1] < capacity:
        # Extended: the buffer was sized to the shorter run's transitions and never
        # wrapped; in the longer run's larger ring it holds the same, as it would have.
        buffer = jax.jit(jax.vmap(lambda b: grow(b, capacity)))(buffer)
        print(f"extending the run to {total_steps:,} steps per seed: its replay buffer grows "
              "as it would have in a run started with this budget", file=sys.stderr, flush=True)
    if buffer is not None and jax.tree_util.tree_map(
            lambda x: x.shape, buffer) != jax.tree_util.tree_map(
            lambda x: x.shape, abstract_state.buffer):
        raise UsageError(f"--resume: checkpoint {restored.step:,} holds a replay buffer "
                         "of another shape than this run's")
    if buffer is None:  # an older checkpoint, or a finished run's last one
        buffer = jax.jit(jax.vmap(program.init))(keys).buffer
        if restored.step < total_steps:
            print(f"checkpoint {restored.step:,} kept no replay buffer (only the latest "
                  "checkpoint of a run in progress does): training goes on from an empty "
                  "buffer, so the result will differ from an uninterrupted run's",
                  file=sys.stderr, flush=True)
    history = restored.meta["history"]
    folder.rewrite_metrics(history)
    print(f"resuming {folder.path} from checkpoint {restored.step:,} "
          f"(of {total_steps:,} steps per seed)", file=sys.stderr, flush=True)
    return (restored.state.replace(buffer=buffer), history,
            float(restored.meta["wall_time_s"]))


def run_chunks(session: Session, on_point: Callable[[list[dict[str, Any]]], None],
               should_stop: Callable[[], bool]) -> NonFinite | None:
    """Trains chunk after chunk (``--eval-every`` steps, then an evaluation) until the
    budget is spent or ``should_stop()``; each evaluation goes to ``metrics.csv`` and
    TensorBoard and then to ``on_point(rows)``; checkpoints are started every
    ``--checkpoint-every`` steps, at the end, and when stopping. Returns where training
    turned non-finite (the bad chunk is not recorded), or ``None``."""
    folder, seeds = session.folder, session.seeds
    total_chunks = session.program.num_evaluations
    for index in range(session.steps // session.chunk_steps, total_chunks):
        if should_stop():
            break
        state, point, training = session.chunk(session.state, True)
        point, training, bad = jax.device_get((point, training, state.nonfinite_iteration))
        found = first_nonfinite(bad, seeds)
        if found is not None:
            return found
        session.state = state
        rows = point_rows(point, seeds, session.wall())
        session.history.extend(rows)
        folder.append_metrics(rows)
        for k, row in enumerate(rows):
            scalars = _eval_scalars(row)
            scalars.update({f"train/{name}": float(np.asarray(value)[k])
                            for name, value in training.items()})
            folder.log_scalars(row["seed"], row["env_steps"], scalars)
        on_point(rows)
        last = index + 1 == total_chunks
        if last or (index + 1) % session.spec.chunks_per_checkpoint == 0 or should_stop():
            session.save()
    return None


def drop_finished_buffer(checkpoints: Checkpoints, step: int) -> None:
    """A finished run needs no replay buffer, unless it is to be extended exactly: deletes
    the one its last checkpoint ``step`` holds, saying so."""
    freed = checkpoints.drop_buffer(step)
    if freed:
        print(f"the finished run's replay buffer ({freed / 2**20:,.0f} MiB) is not "
              "kept (--keep-buffer keeps it, to extend the run exactly with --resume "
              "--steps)", file=sys.stderr, flush=True)


def close(session: Session, keep_buffer: bool) -> list[int]:
    """Waits for the checkpoints, drops a finished run's replay buffer unless
    ``keep_buffer``, closes the event files; returns the checkpoints kept."""
    checkpoints = session.checkpoints
    checkpoints.wait()
    saved = checkpoints.steps()
    if saved and saved[-1] >= session.total_steps and not keep_buffer:
        drop_finished_buffer(checkpoints, saved[-1])
    checkpoints.close()
    session.folder.close_tensorboard()
    return saved


def what_was_kept(folder: RunFolder, saved: Sequence[int]) -> str:
    """What a stopped run leaves, and the command that continues it."""
    if saved:
        return (f"checkpoint {saved[-1]:,} is saved. Continue with:\n"
                f"  {PROG} --out {folder.path} --resume")
    return ("no checkpoint was written; the folder keeps its configuration. Start it again "
            f"with the same command, or with:\n  {PROG} --out {folder.path} --resume")


def train_run(folder: RunFolder, spec: RunSpec, record: dict | None, progress_bar: bool,
              keep_buffer: bool = False, stop: StopRequest | None = None) -> int:
    """Trains (or resumes) the run in ``folder`` (:func:`prepare`, :func:`run_chunks`,
    :func:`close`, then the pictures and summary); returns the exit status. The finished
    run's last checkpoint keeps its replay buffer only with ``keep_buffer``. Ctrl-C and
    SIGTERM are honoured at every moment (:class:`StopRequest`; ``stop`` is the caller's,
    or one held for the call): status 130, with what was kept."""
    with contextlib.ExitStack() as stack:
        if stop is None:
            stop = stack.enter_context(StopRequest())
        return _train(folder, spec, record, progress_bar, keep_buffer, stop)


def _train(folder: RunFolder, spec: RunSpec, record: dict | None, progress_bar: bool,
           keep_buffer: bool, stop: StopRequest) -> int:
    stop.phase = "preparing"
    try:
        session = prepare(folder, spec, record, progress_bar)
    except KeyboardInterrupt:  # a second request while preparing
        saved = folder.checkpoint_steps()  # prepare closed its checkpoints
        print(f"{PROG}: stopped at once before training began; "
              f"{what_was_kept(folder, saved)}", file=sys.stderr, flush=True)
        return INTERRUPTED
    if stop.requested:
        saved = close(session, keep_buffer=True)
        print(f"stopped by {stop.signal_name} before training began; "
              f"{what_was_kept(folder, saved)}", file=sys.stderr, flush=True)
        return INTERRUPTED
    stop.phase = "training"
    progress = Progress(session.total_steps, len(session.seeds), session.steps, progress_bar)

    def show(rows: list[dict[str, Any]]) -> None:
        progress.update(rows[0]["env_steps"],
                        float(np.mean([r["success_rate"] for r in rows])),
                        float(np.mean([r["danger_frequency"] for r in rows])))

    try:
        bad = run_chunks(session, show, lambda: stop.requested)
    except KeyboardInterrupt:  # a second request: the checkpoint being written completes
        progress.close()
        saved = close(session, keep_buffer=True)
        print(f"{PROG}: stopped at once at {session.steps:,} steps per seed; "
              f"{what_was_kept(folder, saved)}", file=sys.stderr, flush=True)
        return INTERRUPTED
    progress.close()
    if bad is not None:
        kept = session.checkpoints.steps()
        kept_note = (f"its last good checkpoint ({kept[-1]:,} steps per seed) is kept"
                     if kept else "it had written no checkpoint yet")
        print(f"{PROG}: error: {bad.message()}; the run stopped and {kept_note}",
              file=sys.stderr, flush=True)
    saved = close(session, keep_buffer)
    if bad is not None:
        return NONFINITE
    if not session.finished:
        print(f"stopped by {stop.signal_name} at {session.steps:,} steps per seed; "
              f"{what_was_kept(folder, saved)}", file=sys.stderr, flush=True)
        return INTERRUPTED
    stop.phase = "finishing"
    try:
        finish(folder, session.program, session.state, session.seeds, session.history,
               session.wall())
    except KeyboardInterrupt:
        print(f"{PROG}: stopped at once; the run finished and checkpoint {saved[-1]:,} is "
              "saved, but not all its pictures and its policy were written: "
              f"python -m ccrjax.evaluate {folder.path} redraws the pictures",
              file=sys.stderr, flush=True)
        return INTERRUPTED
    stop.phase = "done"
    return stop.closing(0)


def _eval_scalars(row: dict[str, Any]) -> dict[str, float]:

    scalars = {f"eval/{name}": row[name] for name in EVAL_METRICS}
    for name in TRAINING_COUNTS:
        scalars[f"train/{name}"] = row[name]
    return scalars


def finish(folder: Any, program: Any, state: Any, seeds: Sequence[int],
           history: list[dict[str, Any]], wall: float) -> None:
    """The summary, the curves and the episode pictures of a finished run."""
    final_steps = history[-1]["env_steps"]
    final_rows = [row for row in history if row["env_steps"] == final_steps]
    summary = folder.write_summary(final_rows, {"wall_time_s": wall})
    curves = Curves()
    steps, values = curves_from_rows(history)
    config = program.config
    label = f"{config.algo} {config.variant}"
    curves.add(label, steps, values)
    plural = "s" if len(seeds) > 1 else ""
    draw_curves(curves, folder.path / "curves.png",
                title=f"{config.scenario}: {label}, {len(seeds)} seed{plural}")
    key = jax.random.fold_in(jax.random.PRNGKey(seeds[0]), PICTURE_KEY)
    record = record_trained_episode(
        program, seed_slice(state, 0), key,
        caption=f"seed {seeds[0]}'s policy (deterministic) in the episode its seed fixes for "
        f"the picture ({unbroken('python -m ccrjax.evaluate --seed N')} draws others)")
    png, gif = write_episode_pictures(record, folder.path)
    policy = export_policy(folder.path, program, state.learner, list(seeds), state.transform)
    print_summary(summary, folder)
    print(f"\npictures: {png}  {gif}  {folder.path / 'curves.png'}")
    print(f"policy: {folder.path / policy.name} (ccrjax.load_policy({str(folder.path)!r}, "
          f"seed={seeds[0]}))")
    if program.transform.extra_obs_size(program.env):  # what only whole episodes give
        print(f"team: ccrjax.load_team({str(folder.path)!r}, seed={seeds[0]}) runs whole "
              f"episodes with the {config.variant} transform's shared features")
    stale = earlier_evaluation(folder.path, final_steps)
    if stale is not None:
        print(f"evaluation.json evaluated the checkpoint at {stale:,} steps per seed, before "
              f"this extension: python -m ccrjax.evaluate {folder.path} evaluates the end")
    if importlib.util.find_spec("tensorboard") is not None:
        print(f"TensorBoard: tensorboard --logdir {folder.tensorboard_dir}")
    elif folder.tensorboard_dir.exists():
        print(f"TensorBoard event files: {folder.tensorboard_dir} (to view them: "
              ".venv/bin/pip install -e '.[tensorboard]')")


def earlier_evaluation(path: Path, steps: int) -> int | None:
    """The checkpoint step of ``path``'s ``evaluation.json`` (``python -m ccrjax.evaluate``'s)
    where it is not ``steps``, the run's end (an extension trained past it); else ``None``."""
    try:
        evaluated = json.loads((path / "evaluation.json").read_text())["checkpoint_env_steps"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return int(evaluated) if evaluated != steps else None


def finished(folder: RunFolder, spec: RunSpec) -> bool:
    """Whether the run in ``folder`` has trained all of ``spec``'s budget and finished: its
    last checkpoint (by name; :func:`resume_finished` reads it) at the budget, a summary of
    that step, and the exported policy, which a run writes last. A run stopped while
    finishing, or an extension stopped before its summary, is not finished."""
    steps = folder.checkpoint_steps()
    total = spec.train.total_env_steps_run
    if not steps or steps[-1] < total or not (folder.path / POLICY_DIR / POLICY_RECORD).exists():
        return False
    try:
        summary = json.loads((folder.path / "summary.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(summary, dict) and summary.get("env_steps_per_seed") == steps[-1]


def resume_finished(folder: RunFolder, spec: RunSpec, keep_buffer: bool,
                    steps_given: bool = False) -> int | None:
    """``--resume`` of a finished run at its own budget: its last checkpoint's training state
    is read (not its replay buffer) to check that it belongs to this run and can be read;
    then nothing is trained or rewritten, and that checkpoint's replay buffer is dropped
    unless ``keep_buffer``. The schedule's rounding notes are printed only where this
    command named ``--steps`` (``steps_given``): the run's own were said when it ran.
    Returns ``None`` where the last checkpoint was unreadable and moved aside (said): the
    run then resumes from the one before, as any stopped run does."""
    program = make_train(spec.train)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in spec.seed_list])
    abstract_state = jax.eval_shape(jax.vmap(program.init), keys)
    checkpoints = Checkpoints(folder.checkpoint_dir, keep=spec.keep_checkpoints)
    try:
        restored = checkpoints.restore_latest(abstract_state.replace(buffer=None), None,
                                              fingerprint(spec.to_dict()))
        report_skipped(restored)
        if restored.step < spec.train.total_env_steps_run:
            return None
        if not keep_buffer:
            drop_finished_buffer(checkpoints, restored.step)
    except CheckpointError as error:  # IncompatibleCheckpoint included
        raise UsageError(f"--resume: {error}") from None
    finally:
        checkpoints.close()
    for note in spec.train.schedule()["notes"] if steps_given else []:  # a larger --steps
        print(f"note: {note}", file=sys.stderr, flush=True)  # that rounds to the budget run
    print(f"{folder.path} is finished ({spec.train.total_env_steps_run:,} environment steps "
          f"per seed): nothing to train; the folder holds "
          f"{folder_bytes(folder.path) / 2**20:,.1f} MiB. python -m ccrjax.evaluate "
          f"{folder.path} evaluates it again; --resume --steps N, N larger, extends it")
    return 0


def print_summary(summary: dict[str, Any], folder: Any) -> None:
    seeds = summary["seeds"]
    print(f"\n{folder.path}: {summary['env_steps_per_seed']:,} environment steps per seed, "
          f"{len(seeds)} seed(s), {summary['wall_time_s']:.0f} s; the folder holds "
          f"{folder_bytes(folder.path) / 2**20:,.1f} MiB")
    print(summary_table(summary))


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.no_compilation_cache and args.compilation_cache != cli.default_cache_dir():
        try:  # a folder the user named must work; the default one may fail quietly
            cli.make_folder(args.compilation_cache, "--compilation-cache")
        except UsageError as error:
            cli.fail(PROG, str(error))
    cli.enable_compilation_cache(None if args.no_compilation_cache else args.compilation_cache)
    with StopRequest() as stop, cli.interrupts_kept():
        try:
            folder, spec, record = open_folder(args)
            if stop.requested:
                print(f"stopped by {stop.signal_name} before the run began; nothing was written",
                      file=sys.stderr, flush=True)
                return INTERRUPTED
            if record is not None and finished(folder, spec):
                status = resume_finished(folder, spec, args.keep_buffer,
                                         steps_given=args.total_env_steps is not None)
                if status is not None:
                    stop.phase = "done"
                    return stop.closing(status)
            status = train_run(folder, spec, record,
                               progress_bar=(not args.no_progress) and sys.stderr.isatty(),
                               keep_buffer=args.keep_buffer, stop=stop)
            return stop.closing(status)
        except UsageError as error:
            cli.fail(PROG, str(error))
        except ValueError as error:  # a configuration value the dataclasses refuse
            options = [o for action in parser._actions for o in action.option_strings]
            cli.fail(PROG, cli.in_option_terms(str(error), OPTION_PREFIXES, options))
        except KeyboardInterrupt:
            print(f"{PROG}: stopped at once before the run began; nothing was written",
                  file=sys.stderr, flush=True)
            return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
