"""CCR's lambda and the pessimistic penalty, searched alike: ``make sweep``, ``make penalty-sweep``.

    python experiments/search.py --variant ccr --out runs/search/ccr
    python experiments/search.py --variant pessimistic --out runs/search/pessimistic
    python experiments/search.py --variant ccr --quick --out /tmp/s     # tiny, for the tests
    python experiments/search.py --variant ccr_reward --regime column   # the study's

Both searches follow one protocol (``docs/protocol.md``, ``experiments/protocol.py``),
fixed before either ran: the same budget per learner, the same selection seeds (100-102,
disjoint from the tables' 0-9), six values spanning more than two orders of magnitude,
and the same selection rule (:mod:`experiments.selection`): the lowest mean danger among the
values whose mean success is at most 5 points below the reference's (value 0), one value for
every scenario and learner, as the paper chose one lambda.

For every scenario and learner one vmapped program trains every value x seed, plus
the value 0 on the same seeds, which is the rule's reference (the penalty 0 is exactly the
plain learner; CCR's lambda 0 leaves the reward unchanged, its robots still observing the
shared scores, so the lambda search also reports the rule against the penalty search's
exact plain runs). Each finished program's cell is written to
``<out>/cells/<scenario>-<algo>.json`` (per-seed final metrics and curves, whether the
plain runs' return plateaued, wall time, device, commit); a re-run skips the cells made
with the same settings. Then: ``search.json`` (everything, and the selected value),
``search.md`` (a table per scenario and learner, the averages over them, the choice),
``tradeoff.png`` (danger against success per value, averaged over the 9 pairs, with the rule's
threshold and choice marked) and
``tradeoff_pairs.png`` (one panel per pair).

Started as several processes (``--coordinator``, ``--num-processes``, ``--process-id``:
:mod:`ccrjax.run.distributed`), each trains its share of every program's runs, on one
machine or several, and process 0 writes the results.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/search.py")

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from ccrjax import cli
from ccrjax.run import distributed
from ccrjax.run.folder import EVAL_METRICS, git_commit, write_atomic
from ccrjax.run.stats import format_mean_ci, plateau_or_undetermined
from ccrjax.run.sweep_grid import (
    REFERENCE_NAME,
    grid_params,
    nonfinite_runs,
    nonfinite_text,
    search_grid,
    search_rows,
    summarise,
)
from ccrjax.training import ALGOS, TrainConfig
from ccrjax.training.grid import GridTraining
from ccrjax.viz.plots import SearchChoice, draw_search_tradeoff
from experiments import protocol
from experiments.cell_identity import cell_is_current, settings_record, training_record
from experiments.ledger import (
    RESULTS,
    STOPPED_KEPT,
    Partial,
    add_checkpoint_option,
    add_no_train_option,
    add_out_options,
    cell_path,
    check_quick_out,
    device_name,
    duration,
    invocation_line,
    open_experiment,
    plan_pairs,
    read_json,
    refuse_untrained,
    train_pairs,
)
from experiments.paper import PAPER_SCENARIOS
from experiments.selection import select

PROG = "python experiments/search.py"
LEARNER_NAMES = protocol.LEARNER_NAMES


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings(protocol.Settings):
    """What every cell of a search is trained with (a cell made otherwise is redone)."""

    variant: str  # the searched transform: ccr, pessimistic or lagrangian
    values: tuple[float, ...]  # the searched values (0 is trained beside them)
    seeds: tuple[int, ...] = protocol.SELECTION_SEEDS

    def config(self, scenario: str, algo: str) -> TrainConfig:
        return protocol.run_config(self, scenario, algo, self.variant)

    @property
    def grid_values(self) -> list[float]:
        """The reference 0 and the searched values."""
        return [0.0, *self.values]


def train_cell(settings: Settings, scenario: str, algo: str, partial: Partial
               ) -> dict[str, Any]:
    """The pair's cell: every value of ``settings.grid_values`` on every seed, in one
    program checkpointed under the pair's name."""
    config = settings.config(scenario, algo)
    values, seeds = list(settings.grid_values), list(settings.seeds)
    parameter, grid_seeds, grid_values = search_grid(config, values, seeds)
    training = GridTraining(config, grid_seeds, grid_params(config, parameter, grid_values))
    training.compile(not settings.quick)
    runs = partial.train(training, f"{scenario}-{algo}")
    history = {m: runs.history[m].tolist() for m in ("return", "success_rate",
                                                      "danger_frequency")}
    reference = runs.history["return"][np.asarray(grid_values) == 0.0]
    return {
        "scenario": scenario, "algo": algo, "settings": settings_record(settings),
        "budget": settings.budget(algo), "training": training_record(config),
        "parameter": parameter, "grid_seeds": grid_seeds, "grid_values": grid_values,
        "rows": search_rows(runs, values, grid_values, seeds),
        "env_steps": runs.history["env_steps"][0].tolist(), "history": history,
        "plain_return_plateau": plateau_or_undetermined(reference),
        "nonfinite_iteration": runs.nonfinite_iteration.tolist(),
        "compile_s": runs.compile_s, "train_s": runs.run_s, "device": device_name(),
        "commit": git_commit(), "date": time.strftime("%Y-%m-%d %H:%M %Z"),
    }


def exact_plain_cells(settings: Settings, out: Path, cells: dict) -> dict | None:
    """For a lambda search (CCR's or a part's), the penalty search's cells of the same pairs,
    when its folder (``pessimistic`` beside ``out``; for CCR's parts in the tables' regime
    also the committed tables' penalty search, which holds the study's pairs) holds them all
    with the same seeds and budgets: their value 0 is exactly the plain learner, while
    lambda 0 still observes the shared scores. ``None`` otherwise (then no check is made)."""
    if protocol.SEARCHED[settings.variant][0] != "lam":
        return None
    # What the penalty search's cells hold when made with these seeds, budgets and
    # evaluations (its own protocol values).
    record = settings_record(dataclasses.replace(
        settings, variant="pessimistic", values=protocol.SEARCHED["pessimistic"][1]))
    folders = [out.parent / "pessimistic"]
    if settings.regime == protocol.DEFAULT_REGIME and settings.variant in protocol.PART_VARIANTS:
        folders.append(RESULTS / "search" / "pessimistic")
    for folder in folders:
        found = {pair: read_json(cell_path(folder, *pair)) for pair in cells}
        if all(cell_is_current(cell, record) for cell in found.values()):
            return found
    return None


def aggregate_rows(settings: Settings, cells: dict) -> list[dict[str, Any]]:
    """Per value, each seed's metric averaged over the pairs, then the mean and interval
    over seeds (the points of ``tradeoff.png``)."""
    rows = []
    for index, value in enumerate(settings.grid_values):
        row: dict[str, Any] = {"value": value, "seeds": list(settings.seeds)}
        for metric in EVAL_METRICS:
            per_pair = np.array([cell["rows"][index][metric]["per_seed"]
                                 for cell in cells.values()])  # [pairs, seeds]
            row[metric] = summarise(per_pair.mean(axis=0), metric)
        rows.append(row)
    return rows


def protocol_pairs(settings: Settings) -> list[set[tuple[str, str]]]:
    """The sets of scenario x learner pairs over which a selection of ``settings`` is the
    protocol's: in the tables' regime, the family's pairs of the paper's scenarios (the
    tables' choice) or the study's pairs (the study's, amendment of 2026-12-01); in another
    regime, and for CCR's parts, the study's alone."""
    study = set(protocol.study_pairs(settings.algos))
    if (settings.regime != protocol.DEFAULT_REGIME
            or settings.variant in protocol.PART_VARIANTS):
        return [study]
    family = protocol.family(settings.algos)
    return [{(s, a) for s in PAPER_SCENARIOS for a in family}, study]


def not_the_protocols(settings: Settings) -> str | None:
    """Why a selection made with ``settings`` is not the protocol's choice (``None`` if it
    is): the rule averages over the pairs of :func:`protocol_pairs`, on the selection
    seeds, over the protocol's values and the regime's evaluations, at the protocol's
    budgets (in the tables' regime also its longer ones, :data:`protocol.LONGER_BUDGETS`;
    in another regime the one its budgets run chose). Such a selection is provisional:
    the tables refuse it."""
    _, values = protocol.SEARCHED[settings.variant]
    family = protocol.family(settings.algos)
    summarised = {(s, a) for s in settings.scenarios for a in settings.algos}
    wanted = min(protocol_pairs(settings), key=lambda pairs: len(pairs ^ summarised))
    left_out = [f"{s}-{a}" for s, a in sorted(wanted - summarised)]
    outside = [f"{s}-{a}" for s, a in sorted(summarised - wanted)]
    reasons = [
        *(["the quick mode"] if settings.quick else []),
        *([f"{len(left_out)} of {len(wanted)} pairs not summarised ({', '.join(left_out)})"]
          if left_out else []),
        *([f"pairs outside the study's ({', '.join(outside)})"] if outside else []),
        *(["the amendment of 2026-12-02 searches no Lagrangian for the on-policy learners"]
          if family == protocol.ON_POLICY_ALGOS and settings.variant == "lagrangian"
          else []),
        *([f"seeds {list(settings.seeds)}"] if settings.seeds != protocol.SELECTION_SEEDS
          else []),
        *([f"values {list(settings.values)}"] if settings.values != values else []),
        *budget_reasons(settings, family, study=wanted == set(protocol.study_pairs(family))),
        *(["other evaluations"] if (settings.eval_every, settings.eval_episodes)
          != (protocol.REGIMES[settings.regime].eval_every, protocol.EVAL_EPISODES) else []),
    ]
    return "; ".join(reasons) or None


def budget_reasons(settings: Settings, family: tuple[str, ...], study: bool = False
                   ) -> list[str]:
    """Why the budgets of ``settings`` are not the protocol's (empty if they are): in the
    tables' regime :func:`protocol_budgets` (``study``: a selection over the study's pairs);
    in another, the budget its budgets run chose (none yet: provisional)."""
    if settings.regime == protocol.DEFAULT_REGIME:
        budgets = protocol_budgets(settings.variant, family, study)
        return ([f"--steps {settings.steps}"] if budgets and
                {a: settings.budget(a) for a in family} not in budgets else [])
    chosen = protocol.REGIME_BUDGETS[settings.regime]
    missing = [a for a in settings.algos if a not in chosen]
    if missing:
        return [f"the {settings.regime} regime's budget of {', '.join(missing)} is not chosen "
                f"yet (experiments/budgets.py --regime {settings.regime})"]
    return ([f"--steps {settings.steps}"]
            if any(settings.budget(a) != chosen[a] for a in settings.algos) else [])


def protocol_budgets(variant: str, family: tuple[str, ...] = ALGOS, study: bool = False
                     ) -> list[dict[str, int]]:
    """The budgets at which ``variant``'s search of the learners ``family`` is the
    protocol's: the off-policy Lagrangian's at its amendment's budget over the tables'
    pairs and at the study's (the protocol's budgets) over the study's pairs (``study``;
    the addition of 2026-12-03), the other off-policy searches at the protocol's budgets
    or its longer ones, the on-policy ones at their family's budget (none for a
    Lagrangian, which the amendment does not search there)."""
    if family == protocol.ON_POLICY_ALGOS:
        if variant == "lagrangian":
            return []
        return [{algo: protocol.ON_POLICY_BUDGET for algo in family}]
    if variant == "lagrangian":
        return [dict(protocol.BUDGETS) if study else
                {algo: protocol.LAGRANGIAN_BUDGET for algo in ALGOS}]
    return [protocol.BUDGETS, protocol.LONGER_BUDGETS]


def selection(settings: Settings, cells: dict, reference_cells: dict | None = None
              ) -> dict[str, Any]:
    """The rule applied to the cells; the reference is each cell's value 0, or the value-0
    rows of ``reference_cells`` (the same pairs) if given."""
    metrics = {m: np.array([[cell["rows"][i][m]["per_seed"] for cell in cells.values()]
                            for i in range(1, len(settings.grid_values))])
               for m in EVAL_METRICS}  # [values, pairs, seeds]
    reference_cells = cells if reference_cells is None else reference_cells
    reference = {m: np.array([reference_cells[pair]["rows"][0][m]["per_seed"]
                              for pair in cells]) for m in EVAL_METRICS}
    chosen = select(protocol.RULE, settings.values, metrics, reference)
    why_not = not_the_protocols(settings)
    return {**chosen, "pairs": len(cells), "protocol": why_not is None,
            "provisional_because": why_not}


def choice_mark(chosen: dict[str, Any]) -> SearchChoice:
    """The rule's decision as drawn on the averaged tradeoff figure (success on its x
    axis: :data:`protocol.RULE` constrains the success rate)."""
    return SearchChoice(value=chosen["value"],
                        threshold=chosen["reference_constraint"] - protocol.RULE.tolerance,
                        label="chosen" if chosen["protocol"] else "provisional choice")


def _cell_text(stats: dict, percent: bool) -> str:
    return format_mean_ci(stats, percent, digits=1)


def rows_table(rows: list[dict], parameter: str, chosen: float | None = None) -> list[str]:
    lines = [f"| {parameter} | danger frequency | success rate | final distance | return |",
             "|---|---|---|---|---|"]
    for row in rows:
        mark = (f" ({REFERENCE_NAME[parameter]})" if row["value"] == 0 else
                " **chosen**" if row["value"] == chosen else "")
        lines.append(f"| {row['value']:g}{mark} | {_cell_text(row['danger_frequency'], True)} | "
                     f"{_cell_text(row['success_rate'], True)} | "
                     f"{_cell_text(row['target_distance'], False)} | "
                     f"{_cell_text(row['return'], False)} |")
    return lines


def search_markdown(result: dict) -> str:
    settings, chosen = result["settings"], result["selection"]
    parameter = result["parameter"]
    lines = [
        f"# Search of {parameter} ({settings['variant']})",
        "",
        *([protocol.quick_note(regime=settings.get("regime", protocol.DEFAULT_REGIME)), ""]
          if settings.get("quick") else []),
        f"Selection seeds {settings['seeds']}{protocol.regime_text(settings)}; budgets per "
        "learner "
        f"{result['budgets']}; evaluation every {settings['eval_every']:,} steps, "
        f"{settings['eval_episodes']} episodes per seed; mean and 95% CI over seeds (Student "
        "t, clipped to each metric's range). Made by:",
        "",
        *(invocation_line(run) for run in result["invocations"]),
        "",
        f"**Rule** (fixed before the search): {chosen['rule']}.",
        "",
        (f"**Chosen: {parameter} = {chosen['value']:g}**" if chosen.get("protocol") else
         f"**Provisional, not the protocol's choice ({chosen.get('provisional_because')}): "
         f"{parameter} = {chosen['value']:g}**")
        + (f" (no value met the rule: the one closest to the success of {parameter} 0, "
           f"{REFERENCE_NAME[parameter]})" if chosen["fallback"] else "") + ".",
        *(["", f"The same rule with the penalty search's value-0 runs (exactly plain, the same "
           f"seeds, pairs and budgets) as the reference instead of lambda 0 (whose robots "
           f"observe the shared scores): {parameter} = "
           f"{result['selection_against_exact_plain']['value']:g}."]
          if result.get("selection_against_exact_plain") else []),
        "",
        nonfinite_text(result["nonfinite"], f"the {result['runs']} runs"),
        "",
        "## Averaged over the scenario x learner pairs",
        "",
        *rows_table(result["aggregate"], parameter, chosen["value"]),
        "",
    ]
    for pair in result["pairs"]:
        flag = pair["plain_return_plateau"].get("plateaued")
        lines += [f"## {pair['scenario']}, {LEARNER_NAMES[pair['algo']]}",
                  "",
                  f"Return of {parameter} 0 ({REFERENCE_NAME[parameter]}) plateaued at "
                  f"this budget: {protocol.PLATEAU_WORDS[flag]}; program: "
                  f"{duration(pair['train_s'])} training, {duration(pair['compile_s'])} "
                  f"compiling on {pair['device']} at `{pair['commit']}`.",
                  "", *rows_table(pair["rows"], parameter, chosen["value"]), ""]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description="Search CCR's lambda, the pessimistic penalty "
                        "or the Lagrangian's cost limit over every scenario and learner under "
                        "one protocol and rule.")
    parser.add_argument("--variant", choices=sorted(protocol.SEARCHED), required=True,
                        help="ccr (lambda), pessimistic (penalty) or lagrangian (cost limit); "
                        "for the study, CCR's parts ccr_reward and ccr_perfect (lambda)")
    parser.add_argument("--values", type=cli.float_in(0.0, low_open=True), nargs="+",
                        default=None, help="searched values, > 0 (default: the protocol's six "
                        "of the variant); 0, the rule's reference, is always trained beside them")
    parser.add_argument("--seeds", type=cli.int_in(2, 1024), default=None,
                        help="seeds per value, at least 2 (default: "
                        f"{len(protocol.SELECTION_SEEDS)}, the selection seeds from 100)")
    parser.add_argument("--seed-offset", type=cli.seed_int, default=protocol.SELECTION_SEEDS[0],
                        help="first seed (default: %(default)s; the tables use 0-9)")
    parser.add_argument("--steps", type=cli.positive_int, default=None,
                        help="environment steps per run for every learner (default: the "
                        f"protocol's budgets, {protocol.budgets_text()}; the Lagrangian's "
                        f"{protocol.LAGRANGIAN_BUDGET:,}, over the study's pairs the "
                        "study's)")
    parser.add_argument("--scenarios", nargs="+", choices=PAPER_SCENARIOS, default=None,
                        help="scenarios (default: all three; for CCR's parts or another "
                        "regime, the study's: " + " ".join(protocol.STUDY_SCENARIOS) + ")")
    parser.add_argument("--algos", nargs="+", choices=protocol.EXPERIMENT_ALGOS,
                        default=None,
                        help="learners, of one family (default: the paper's three, or for "
                        "CCR's parts or another regime the study's " + " ".join(
                            protocol.STUDY_ALGOS) + "; ippo mappo: the on-policy family, "
                        "whose rule runs over its own 6 pairs)")
    parser.add_argument("--regime", choices=tuple(protocol.REGIMES),
                        default=protocol.DEFAULT_REGIME,
                        help="the hazards' placement, the team's formation and the episode "
                        "length (docs/protocol.md, amendment of 2026-12-01; default: "
                        "%(default)s, the tables'); another regime searches the study's pairs "
                        "at its own evaluation interval and budget")
    parser.add_argument("--quick", action="store_true",
                        help=protocol.quick_help())
    add_out_options(parser, "search/<variant> (the on-policy learners': "
                    "search_on_policy/<variant>)",
                    default_text="runs/search/<variant>, the on-policy learners' "
                    "runs/search_on_policy/<variant>, another regime's runs/search_<regime>/"
                    "<variant>")
    add_checkpoint_option(parser)
    add_no_train_option(parser)
    distributed.add_options(parser)
    return parser


def settings_from(args: argparse.Namespace) -> Settings:
    _, default_values = protocol.SEARCHED[args.variant]
    regime = protocol.REGIMES[args.regime]
    study = args.regime != protocol.DEFAULT_REGIME or args.variant in protocol.PART_VARIANTS
    algos = args.algos or list(protocol.STUDY_ALGOS if study else ALGOS)
    scenarios = args.scenarios or list(protocol.STUDY_SCENARIOS if study else PAPER_SCENARIOS)
    try:
        protocol.family(algos)
    except ValueError as error:
        raise cli.UsageError(str(error)) from None
    values = tuple(sorted({float(v) for v in (args.values or default_values)}))
    fields: dict[str, Any] = {"variant": args.variant, "values": values,
                              "scenarios": tuple(dict.fromkeys(scenarios)),
                              "algos": tuple(dict.fromkeys(algos)), "regime": args.regime,
                              "eval_every": regime.eval_every}
    if args.quick:
        fields.update(quick=True, steps=protocol.QUICK_STEPS * regime.quick_scale,
                      eval_every=protocol.QUICK_EVAL_EVERY * regime.quick_scale,
                      eval_episodes=protocol.QUICK_EVAL_EPISODES)
    if args.steps is not None:
        fields["steps"] = args.steps
    elif (args.variant == "lagrangian" and not args.quick
          and args.regime == protocol.DEFAULT_REGIME
          and {(s, a) for s in scenarios for a in algos} != set(protocol.study_pairs(algos))):
        fields["steps"] = protocol.LAGRANGIAN_BUDGET  # the study's pairs: the study's budget
    count = args.seeds or (2 if args.quick else len(protocol.SELECTION_SEEDS))
    fields["seeds"] = tuple(range(args.seed_offset, args.seed_offset + count))
    problem = protocol.seed_overlap(fields["seeds"], args.seed_offset,
                                    ("the tables'", "the budgets'"))
    if problem:  # --quick too, as the tables and the budgets refuse
        raise cli.UsageError(problem)
    return Settings(**fields)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    distributed.initialize(PROG, args)
    # A family's and a regime's own folder.
    on_policy = set(args.algos or ()) <= set(protocol.ON_POLICY_ALGOS) and bool(args.algos)
    regime = "" if args.regime == protocol.DEFAULT_REGIME else f"_{args.regime}"
    out = args.out or Path(f"runs/search{'_on_policy' if on_policy else ''}{regime}"
                           ) / args.variant

    def settings_of() -> Settings:
        check_quick_out(args.quick, args.out)
        settings = settings_from(args)
        for scenario in settings.scenarios:  # every configuration validated before compiling
            for algo in settings.algos:
                settings.config(scenario, algo)
        if args.no_train:
            refuse_untrained({f"{s}-{a}": cell_path(out, s, a) for s in settings.scenarios
                              for a in settings.algos}, settings_record(settings), out)
        return settings

    settings, ledger = open_experiment(PROG, argv, out, args.force, settings_of)
    runs = len(settings.grid_values) * len(settings.seeds)
    cells, todo, progress = plan_pairs(
        settings, out, runs, f"{len(settings.grid_values)} values x {len(settings.seeds)} "
        f"seeds = {runs} runs each")
    partial = Partial(out, args.checkpoint_minutes)
    cells.update(train_pairs(todo, out, partial, ledger, progress,
                             lambda s, a: train_cell(settings, s, a, partial)))
    ledger.record(len(todo), finished=True)
    if not distributed.is_primary():  # process 0 writes the summary
        return 0
    ordered = {pair: cells[pair] for pair in
               [(s, a) for s in settings.scenarios for a in settings.algos]}
    parameter, _ = protocol.SEARCHED[settings.variant]
    plain_cells = exact_plain_cells(settings, out, ordered)
    result = {
        "settings": settings_record(settings), "parameter": parameter,
        "budgets": {a: settings.budget(a) for a in settings.algos},
        "invocations": ledger.invocations,
        "selection": selection(settings, ordered),
        "selection_against_exact_plain": (None if plain_cells is None else
                                          selection(settings, ordered, plain_cells)),
        "aggregate": aggregate_rows(settings, ordered),
        "runs": runs * len(ordered),
        "nonfinite": [line for (s, a), cell in ordered.items()
                      for line in nonfinite_runs(cell, f"{s}, {LEARNER_NAMES[a]}")],
        "pairs": [{k: cell[k] for k in ("scenario", "algo", "rows", "plain_return_plateau",
                                         "train_s", "compile_s", "device", "commit")}
                  for cell in ordered.values()],
    }
    write_atomic(out / "search.json", json.dumps(result, indent=1) + "\n")
    write_atomic(out / "search.md", search_markdown(result))
    quick = protocol.QUICK_FIGURE if settings.quick else ""
    title = f"{quick}{settings.variant}: averaged over {len(ordered)} scenario x learner pair(s)"
    draw_search_tradeoff({title: result["aggregate"]}, parameter, out / "tradeoff.png",
                         choices={title: choice_mark(result["selection"])})
    draw_search_tradeoff({f"{quick}{s}, {LEARNER_NAMES[a]}": cell["rows"]
                          for (s, a), cell in ordered.items()}, parameter,
                         out / "tradeoff_pairs.png")
    print(search_markdown(result))
    chosen = result["selection"]
    print(f"chose {parameter} = {chosen['value']:g}"
          + ("" if chosen["protocol"] else f" (provisional: {chosen['provisional_because']})")
          + f"; wrote {out / 'search.md'}, search.json, tradeoff.png, tradeoff_pairs.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, STOPPED_KEPT))
