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
and the same compiled chunk runs from it. Ctrl-C and SIGTERM (:mod:`ccrjax.terminal`, from the
command's first statement) stop at once before training begins; while training, the first
finishes the current chunk and saves a checkpoint, a second stops within seconds; each exits
with status 130 saying what was kept. A run stopped before its first checkpoint starts again
in the same folder. Mistakes on the command line get one line and exit status 2. The run
folder and its resumption live in :mod:`ccrjax.run` (``resume``, ``session``, ``finish``).
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python -m ccrjax.train")

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ccrjax import cli
from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.agents.ppo import PPOConfig
from ccrjax.cli import UsageError
from ccrjax.envs.scenarios import SCENARIOS, Layout
from ccrjax.registry import learner_entry, learner_names, transform_entry, transform_names
from ccrjax.run import session as sessions
from ccrjax.run.finish import finish, finished, resume_finished
from ccrjax.run.folder import TRAIN_COMMAND, RunFolder
from ccrjax.run.resume import open_folder, what_was_kept
from ccrjax.run.spec import RunSpec
from ccrjax.terminal import INTERRUPTED, Progress, Stop
from ccrjax.training import TrainConfig, default_budgets
from ccrjax.transforms import Pessimistic
from ccrjax.transforms.ccr import CCR, CCRConfig, DangerFlags
from ccrjax.transforms.lagrangian import Lagrangian

PROG = TRAIN_COMMAND
# The transforms' searched numbers, each an option of its own (not --<prefix>-<field>): the
# option, the configuration class, its field and the option's converter.
SHORTHANDS = (("--lam", CCRConfig, "lam", cli.non_negative_float),
              ("--penalty", Pessimistic, "penalty", cli.non_negative_float),
              ("--cost-limit", Lagrangian, "cost_limit", cli.float_in(0.0, 1.0)))
# The configuration dataclasses whose fields are options, and the options' prefix
# (--ddpg-gamma is DDPGConfig.gamma): errors name the option, not the field.
# DangerFlags' comm_range is --ccr-comm-range too.
# Registered learners and transforms add theirs (option_prefixes()).
OPTION_PREFIXES = {"CCRConfig": "ccr", "DangerFlags": "ccr", "Layout": "layout"}
# The layout's fields that are options: the regime's two knobs (hazard placement, team
# formation) and the arena that a long column needs; the start box and target area stay.
LAYOUT_OPTION_FIELDS = ("hazard_x_range", "hazard_y_range", "formation", "column_spacing",
                        "column_lateral", "arena_half_extent")
# CCRConfig's fields of the dynamics model: no option of the variants without one.
CCR_MODEL_FIELDS = ("degree", "ridge", "tolerance")
# A new run's defaults are make train's: MADDPG with CCR on the hidden obstacle.
DEFAULT_TRAIN = TrainConfig(scenario="hidden_obstacle", variant="ccr")
# The options that set a TrainConfig field (option, field, converter, extras): the parser
# and resolve() both read this table; the option's value lands in args.<field>. Choices
# and shown defaults given as functions are read when the parser is built, so that the
# registry's learners, variants and scenarios (plugins included) are all offered.
TRAIN_OPTIONS: tuple[tuple[str, str, Any, dict[str, Any]], ...] = (
    ("--scenario", "scenario", None, {"choices": SCENARIOS}),
    ("--algo", "algo", None, {"choices": learner_names}),
    ("--variant", "variant", None, {"choices": transform_names}),
    ("--steps", "total_env_steps", cli.positive_int,
     {"shown": lambda: ", ".join(f"{v:,} for {k}" for k, v in default_budgets().items())}),
    ("--num-envs", "num_envs", cli.int_in(1, 65536),
     {"shown": lambda: ", ".join(f"{learner_entry(name).default_num_envs} for {name}"
                                 for name in learner_names())}),
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
        description="Train a robot team (IDDPG, MADDPG, MAAC, IPPO or MAPPO; plain, pessimistic, "
        "CCR or a Lagrangian cost constraint) on one emergency scenario, all seeds at once, "
        "into a run folder.",
        epilog="Every option left out keeps its default; with --resume, the run's own "
        "configuration (config.json) is used and options that contradict it are refused.",
    )
    # Every option's help and default come from the dataclass field it sets.
    run = parser.add_argument_group("the run")
    for option, field, convert, extra in TRAIN_OPTIONS:
        extra = {key: value() if callable(value) else value for key, value in extra.items()}
        cli.add_field_option(run, option, DEFAULT_TRAIN, field, convert, **extra)
    for option, owner, field, convert in SHORTHANDS:
        cli.add_field_option(run, option, owner(), field, convert)
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
    folder.add_argument("--plugin", action="append", metavar="MODULE", help=cli.PLUGIN_HELP)

    for prefix, (config_type, names) in learner_option_groups().items():
        cli.add_dataclass_options(parser, config_type, prefix,
                                  f"{' / '.join(n.upper() for n in names)} hyperparameters",
                                  # the learner's name says it (maddpg / iddpg, mappo / ippo)
                                  exclude=("centralised_critic",) if config_type in (
                                      DDPGConfig, PPOConfig) else ())
    cli.add_dataclass_options(parser, CCRConfig, OPTION_PREFIXES["CCRConfig"],
                              "CCR parameters (ccr and its parts ccr_scores, ccr_reward, "
                              "ccr_perfect; --ccr-comm-range also danger_flags)",
                              exclude=("lam",))
    cli.add_dataclass_options(
        parser, Layout, OPTION_PREFIXES["Layout"],
        "regime: hazard placement and team formation (a value starting with '-' is written "
        "--layout-hazard-y-range=-1,1)",
        exclude=[f.name for f in dataclasses.fields(Layout) if f.name not in LAYOUT_OPTION_FIELDS])
    for prefix, (transform_type, names) in transform_option_groups().items():
        cli.add_dataclass_options(parser, transform_type, prefix,
                                  f"{' / '.join(names)} parameters",
                                  exclude=("cost_limit",) if transform_type is Lagrangian
                                  else ())  # --cost-limit
    return parser


def option_groups(entries: list[tuple[str, str | None, type]]
                  ) -> dict[str, tuple[type, list[str]]]:
    """Each option prefix of ``entries`` (name, prefix, its dataclass), with its dataclass and
    the names that share it (``ddpg``: ``DDPGConfig``, iddpg and maddpg)."""
    groups: dict[str, tuple[type, list[str]]] = {}
    for name, prefix, cls in entries:
        if prefix is not None:
            groups.setdefault(prefix, (cls, []))[1].append(name)
    return groups


def learner_option_groups() -> dict[str, tuple[type, list[str]]]:
    """The registered learners' option groups (their configs' fields)."""
    return option_groups([(name, learner_entry(name).option_prefix,
                           learner_entry(name).config_type) for name in learner_names()])


def transform_option_groups() -> dict[str, tuple[type, list[str]]]:
    """The option groups of transforms registered with a prefix (the built-in ones have
    their own options: --penalty, --lam, --ccr-*)."""
    return option_groups([(name, transform_entry(name).option_prefix,
                           transform_entry(name).type) for name in transform_names()])


def option_prefixes() -> dict[str, str]:
    """Configuration class name -> its options' prefix, for errors in the options' terms."""
    prefixes = dict(OPTION_PREFIXES)
    for groups in (learner_option_groups(), transform_option_groups()):
        prefixes.update({cls.__name__: prefix for prefix, (cls, _) in groups.items()})
    return prefixes


def group_overrides(args: argparse.Namespace, groups: dict[str, tuple[type, list[str]]],
                    option: str, chosen: str) -> dict[str, Any]:
    """The fields given by the options of ``groups`` (:func:`learner_option_groups` or
    :func:`transform_option_groups`); options of a group that ``chosen`` (the ``option``'s
    value) is not in are refused with one line."""
    fields: dict[str, Any] = {}
    for prefix, (_, names) in groups.items():
        overrides = cli.dataclass_overrides(args, prefix)
        if overrides and chosen not in names:
            raise UsageError(f"--{prefix}-* options apply to {option} {listed(names)}, "
                             f"not {chosen}")
        fields.update(overrides)
    return fields


def listed(names: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)


def ccr_option_variants(field: str) -> list[str]:
    """The variants that take ``CCRConfig``'s ``field`` (``--lam``, ``--ccr-*``): CCR and its
    parts (:mod:`ccrjax.transforms.ccr.parts`), ``lam`` only where the intrinsic reward is
    added, the model's ``degree``, ``ridge`` and ``tolerance`` only where the model detects;
    ``comm_range`` also for ``danger_flags``."""
    variants = []
    for variant in transform_names():
        transform_type = transform_entry(variant).type
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
    if algo != train.algo:  # another learner: its own defaults, budget and environments
        fields["learner"] = None
        fields.setdefault("total_env_steps", None)
        fields.setdefault("num_envs", None)
    if variant != train.variant:
        fields["transform"] = None

    learner = group_overrides(args, learner_option_groups(), "--algo", algo)
    own = group_overrides(args, transform_option_groups(), "--variant", variant)
    if args.penalty is not None and variant != "pessimistic":
        raise UsageError(f"--penalty applies to --variant pessimistic, not {variant}")
    if args.cost_limit is not None:
        if variant != "lagrangian":
            raise UsageError(f"--cost-limit applies to --variant lagrangian, not {variant}")
        own["cost_limit"] = args.cost_limit
    ccr = cli.dataclass_overrides(args, "ccr")
    if args.lam is not None:
        ccr["lam"] = args.lam
    for field in ccr:  # each --ccr-* option (and --lam) only where the variant uses it
        allowed = ccr_option_variants(field)
        if variant not in allowed:
            option = "--lam" if field == "lam" else f"--ccr-{field.replace('_', '-')}"
            names = " or ".join([", ".join(allowed[:-1]), allowed[-1]] if len(allowed) > 1
                                else allowed)
            raise UsageError(f"{option} applies to --variant {names}, not {variant}")
    layout = cli.dataclass_overrides(args, "layout")
    if layout:
        fields["layout_params"] = {**train.layout_params, **layout}
    train = dataclasses.replace(train, **fields)
    if learner:
        train = dataclasses.replace(train, learner=dataclasses.replace(
            train.resolved_learner, **learner))
    if own:
        train = dataclasses.replace(train, transform=dataclasses.replace(
            train.resolved_transform, **own))
    if args.penalty is not None:
        train = dataclasses.replace(train, transform=Pessimistic(penalty=args.penalty))
    if ccr:
        transform = train.resolved_transform  # CCR or one of its parts, or DangerFlags
        transform = (type(transform)(dataclasses.replace(transform.config, **ccr))
                     if isinstance(transform, CCR) else dataclasses.replace(transform, **ccr))
        train = dataclasses.replace(train, transform=transform)
    train = dataclasses.replace(train, learner=train.resolved_learner,
                                transform=train.resolved_transform,
                                total_env_steps=train.budget)

    run_fields = {field: getattr(args, field) for _, field, _ in SPEC_OPTIONS
                  if getattr(args, field) is not None}
    if base is None:
        return RunSpec(train=train, **run_fields)
    return dataclasses.replace(base, train=train, **run_fields)


# ---------------------------------------------------------------------------- training
def train_run(folder: RunFolder, spec: RunSpec, record: dict | None, progress_bar: bool,
              keep_buffer: bool, stop: Stop) -> int:
    """Trains (or resumes) the run in ``folder`` (:func:`ccrjax.run.session.prepare`, the
    chunk loop, closing, then the pictures and policy); returns the exit status. The
    finished run's last checkpoint keeps its replay buffer only with ``keep_buffer``.
    ``stop`` is the process's (:mod:`ccrjax.terminal`): until training begins a signal ends
    the process at once, keeping what is on disk; then the first one ends the current chunk
    and saves a checkpoint, and a second ends the process within seconds."""
    stop.phase, stop.kept = "starting", lambda: what_was_kept(folder, folder.checkpoint_steps())
    session = sessions.prepare(folder, spec, record, progress_bar)
    stop.kept = lambda: (f"at {session.steps:,} steps per seed, "
                         + what_was_kept(folder, session.checkpoints.steps()))
    stop.phase = "working"
    progress = Progress(session.total_steps, len(session.seeds), session.steps, progress_bar)

    def show(rows: list[dict[str, Any]]) -> None:
        progress.update(rows[0]["env_steps"],
                        float(np.mean([r["success_rate"] for r in rows])),
                        float(np.mean([r["danger_frequency"] for r in rows])))

    bad = sessions.run_chunks(session, show, lambda: stop.requested)
    progress.close()
    if bad is not None:
        kept = session.checkpoints.steps()
        kept_note = (f"its last good checkpoint ({kept[-1]:,} steps per seed) is kept"
                     if kept else "it had written no checkpoint yet")
        print(f"{PROG}: error: {bad.message()}; the run stopped and {kept_note}",
              file=sys.stderr, flush=True)
    saved = sessions.close(session, keep_buffer)
    if bad is not None:
        return NONFINITE
    if not session.finished:
        print(f"{PROG}: stopped by {stop.signal_name} at {session.steps:,} steps per seed; "
              f"{what_was_kept(folder, saved)}", file=sys.stderr, flush=True)
        return INTERRUPTED
    stop.when = "the run has finished; stopping once its pictures and policy are written"
    stop.kept = (f"the run finished and checkpoint {saved[-1]:,} is saved, but not all its "
                 f"pictures and its policy were written: python -m ccrjax.evaluate "
                 f"{folder.path} redraws the pictures")
    finish(folder, session.program, session.state, session.seeds, session.history,
           session.wall())
    stop.phase = "done"
    return stop.closing(0)


def main(argv: Sequence[str] | None = None) -> int:
    """The command: parse, open the folder, train or resume, report; returns the status."""
    with terminal.stopping(PROG) as stop:
        return _main(list(sys.argv[1:] if argv is None else argv), stop)


def _main(argv: list[str], stop: Stop) -> int:
    try:
        cli.load_plugins(argv)
    except UsageError as error:
        cli.fail(PROG, str(error))
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.no_compilation_cache and args.compilation_cache != cli.default_cache_dir():
        try:  # a folder the user named must work; the default one may fail quietly
            cli.make_folder(args.compilation_cache, "--compilation-cache")
        except UsageError as error:
            cli.fail(PROG, str(error))
    cli.enable_compilation_cache(None if args.no_compilation_cache else args.compilation_cache)
    try:
        folder, spec, record = open_folder(args.out, args.resume,
                                           lambda saved: resolve(args, saved))
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
        message = str(error)
        for option, owner, field, _ in SHORTHANDS:  # Lagrangian.cost_limit is --cost-limit
            message = message.replace(f"{owner.__name__}.{field}", option)
        cli.fail(PROG, cli.in_option_terms(message, option_prefixes(), options))


if __name__ == "__main__":
    sys.exit(main())
