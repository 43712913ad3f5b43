"""``constrained.json``, ``constrained.md`` and the multiplier figures of the constrained
baseline's tables (:mod:`experiments.constrained`), from its Lagrangian cells and the
committed cells of the other variants and searches (:mod:`experiments.constrained_analysis`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ccrjax.run.stats import format_mean_ci, mean_ci
from ccrjax.viz.plots import Curves, draw_curves
from experiments import protocol
from experiments.constrained_analysis import (
    BASELINES,
    PAIRS,
    aggregates,
    hypotheses,
    pair_rows,
    rule_value_rows,
    scorecard,
    selection_at,
)
from experiments.ledger import read_json, repo_relative
from experiments.tables_grid import LEARNER_NAMES, SCENARIO_NAMES, cell_stem

NAMES = {"plain": "plain", "pessimistic": "pessimistic", "ccr": "CCR",
         "lagrangian": "Lagrangian"}
PARAMETERS = {"ccr": "lam", "pessimistic": "penalty", "lagrangian": "cost_limit"}


def baseline_cells(tables: Path, seeds: tuple[int, ...]) -> dict[tuple[str, str, str], dict]:
    """The plain, pessimistic and CCR cells of the tables in ``tables`` (their seeds must be
    ``seeds``); ``ValueError`` naming what is missing."""
    cells = {}
    for scenario, algo in PAIRS:
        for variant in BASELINES:
            path = tables / "cells" / f"{cell_stem(scenario, algo, variant)}.json"
            cell = read_json(path)
            if not cell:
                raise ValueError(f"no cell at {path}")
            if tuple(cell["seeds"]) != tuple(seeds):
                raise ValueError(f"{path} holds seeds {cell['seeds']}, not {list(seeds)}")
            cells[(scenario, algo, variant)] = cell
    return cells


def search_cells(folder: Path) -> dict[tuple[str, str], dict] | None:
    """A search's 9 cells, or ``None`` if any is missing."""
    cells = {pair: read_json(folder / "cells" / f"{pair[0]}-{pair[1]}.json") for pair in PAIRS}
    return cells if all(cells.values()) else None


def selections(searches: Path, lagrangian_search: Path, steps: int) -> dict[str, Any]:
    """The rule at ``steps`` for each search (what is missing said in words)."""
    found = {}
    for variant, folder in (("ccr", searches / "ccr"), ("pessimistic", searches / "pessimistic"),
                            ("lagrangian", lagrangian_search)):
        cells = search_cells(folder)
        found[variant] = (selection_at(cells, steps) if cells else
                          {"missing": f"{folder} lacks some of the 9 pairs' cells"})
    return found


def rule_value_cells(folders: Sequence[Path], seeds: tuple[int, ...], steps: int,
                     values: dict[str, float]) -> tuple[dict[tuple[str, str, str], dict],
                                                        dict[str, str], str | None]:
    """The pessimistic and CCR table cells trained with ``values`` (the rule's choices at
    the budget, where they are not the tables') on ``seeds`` and evaluated at ``steps``,
    each variant's from the first of ``folders`` that holds all 9 of its cells (tables made
    at the budget, or tables of a longer budget on the same seeds: a run's first ``steps``
    are the run of that budget, ``docs/protocol.md``); the folder each variant's cells came
    from; and, if some are missing, what makes them (``None`` when all are there)."""

    def found_in(folder: Path, variant: str) -> dict[tuple[str, str, str], dict] | None:
        parameter, cells = PARAMETERS[variant], {}
        for scenario, algo in PAIRS:
            cell = read_json(folder / "cells" / f"{cell_stem(scenario, algo, variant)}.json")
            if (not cell or tuple(cell["seeds"]) != tuple(seeds)
                    or set(cell["params"].get(parameter, [])) != {values[variant]}
                    or steps not in [int(x) for x in cell["history"]["env_steps"][0]]):
                return None
            cells[(scenario, algo, variant)] = cell
        return cells

    cells, sources, missing = {}, {}, []
    for variant in values:
        for folder in folders:
            if (found := found_in(folder, variant)) is not None:
                cells.update(found)
                sources[variant] = repo_relative(folder)
                break
        else:
            missing.append(variant)
    if not missing:
        return cells, sources, None
    given = " ".join(f"--{'lam' if v == 'ccr' else 'penalty'} {x:g}" for v, x in values.items())
    target = folders[0]
    return cells, sources, (
        f"the {' and '.join(NAMES[v] for v in missing)} cells of the rule's values are in none "
        f"of {', '.join(repo_relative(f) for f in folders)} (`python experiments/tables.py "
        f"--steps {steps} {given} --variants {' '.join(missing)} --out "
        f"{repo_relative(target)} --force`)")


def multiplier_figures(lagrangian: dict[tuple[str, str], dict], cost_limit: float, out: Path,
                       quick: bool) -> list[Path]:
    """Per scenario, the multiplier's path, its input and the evaluated danger over
    training, one curve per learner (mean, 95% band, seeds faint), the limit dashed."""
    paths = []
    metrics = ("lagrange_multiplier", "lagrange_cost", "danger_frequency")
    for scenario in sorted({s for s, _ in lagrangian}):
        curves = Curves()
        for (s, algo), cell in lagrangian.items():
            if s == scenario:
                history = cell["history"]
                curves.add(LEARNER_NAMES[algo], np.asarray(history["env_steps"][0]),
                           {m: np.asarray(history[m]) for m in metrics})
        path = out / f"multiplier_{scenario}.png"
        title = (f"{protocol.QUICK_FIGURE if quick else ''}{SCENARIO_NAMES[scenario]}: the "
                 f"Lagrangian's multiplier, cost limit {cost_limit:g}")
        draw_curves(curves, path, metrics=metrics, title=title,
                    lines={m: (cost_limit, "cost limit") for m in metrics[1:]})
        paths.append(path)
    return paths


def report(lagrangian: dict[tuple[str, str], dict], settings: Any, tables: Path,
           searches: Path, lagrangian_search: Path, sources: dict[str, str], out: Path,
           invocations: list[dict[str, Any]], resamples: int = 2000,
           at_budget: Sequence[Path] = ()) -> tuple[dict, str, list[Path]]:
    """The result, its markdown and the figures written into ``out`` (``resamples``: the
    bootstrap's, for rliable's intervals). Where the rule at the budget chooses another
    penalty or lambda than the tables', the pessimistic and CCR cells of those values at the
    budget (from the first of the ``at_budget`` folders holding them: the amendment's
    "reported beside", :func:`rule_value_cells`) are read and compared too."""
    steps = settings.budget(PAIRS[0][1])
    cells = baseline_cells(tables, settings.seeds)
    cells.update({(s, a, "lagrangian"): cell for (s, a), cell in lagrangian.items()})
    rows = pair_rows(cells, steps, settings.cost_limit)
    used = {variant: cells[(*PAIRS[0], variant)]["params"] for variant in ("ccr", "pessimistic")}
    chosen = selections(searches, lagrangian_search, steps)
    differ = {v: float(chosen[v]["value"]) for v in ("pessimistic", "ccr")
              if "value" in chosen[v]
              and float(chosen[v]["value"]) not in used[v].get(PARAMETERS[v], [])}
    at_rule = {"values": differ, "folders": [repo_relative(f) for f in at_budget], "sources": {},
               "missing": None, "pairs": {}}
    if differ:
        if not at_budget:
            at_rule["missing"] = "no folder of their cells was given"
        else:
            extra, at_rule["sources"], at_rule["missing"] = rule_value_cells(
                at_budget, settings.seeds, steps, differ)
            if at_rule["missing"] is None:
                at_rule["pairs"] = {f"{s}-{a}": row for (s, a), row in
                                    rule_value_rows(extra, rows, steps).items()}
    result = {
        "settings": {"steps": steps, "seeds": list(settings.seeds),
                     "cost_limit": settings.cost_limit, "quick": settings.quick},
        "sources": {**sources, "tables": repo_relative(tables),
                    "searches": repo_relative(searches),
                    "lagrangian_search": repo_relative(lagrangian_search)},
        "invocations": invocations,
        "selections_at_budget": chosen,
        "at_rule_values": at_rule,
        "tables_values": {v: {k: sorted(set(x)) for k, x in p.items()} for v, p in used.items()},
        "pairs": {f"{s}-{a}": row for (s, a), row in rows.items()},
        "aggregates": aggregates(rows, resamples),
        "hypotheses": hypotheses(rows, settings.cost_limit),
        "scorecard": scorecard(rows),
        "commits": sorted({cell["commit"] for cell in lagrangian.values()}),
        "devices": sorted({cell["device"] for cell in lagrangian.values()}),
    }
    figures = multiplier_figures(lagrangian, settings.cost_limit, out, settings.quick)
    return result, markdown(result), figures


def _cell(values: list[float]) -> str:
    return format_mean_ci(mean_ci(values, bounds=(0.0, 1.0)), percent=True)


def _mark(test: dict[str, Any]) -> str:
    return "" if not test["significant"] else (" (lower*)" if test["difference"] < 0
                                               else " (higher*)")


def rule_value_lines(found: dict[str, Any] | None) -> list[str]:
    """The section on pessimistic and CCR at the rule's choices at the budget."""
    if not found or not found["values"]:
        return []
    values = ", ".join(f"{PARAMETERS[v]} {x:g}" for v, x in found["values"].items())
    lines = ["", "## Pessimistic and CCR at the rule's choices at this budget", "",
             f"The rule at this budget chose {values}, not the tables' values, so their cells "
             "at this budget are reported beside (docs/protocol.md, amendment of "
             "2026-12-02). `*`: the Lagrangian against that row, Welch p < 0.05."]
    if found["missing"]:
        return lines + ["", f"Not yet: {found['missing']}."]
    lines += ["", "Read from: " + "; ".join(
        f"{NAMES[v]}'s cells, `{folder}`" for v, folder in found["sources"].items())
        + " (a run of a longer budget is read at this one: its first steps are the run of"
        " this budget)."]
    lines += ["", "| pair | variant | danger | success | training danger |",
              "|---|---|---|---|---|"]
    for key, row in found["pairs"].items():
        scenario, algo = key.split("-")
        for variant, values_of in row["variants"].items():
            marks = {m: _mark(row["welch"][variant][m]) for m in row["welch"][variant]}
            lines.append(
                f"| {SCENARIO_NAMES[scenario]}, {LEARNER_NAMES[algo]} | {NAMES[variant]} "
                f"({PARAMETERS[variant]} {found['values'][variant]:g}) | "
                f"{_cell(values_of['danger_frequency'])}{marks['danger_frequency']} | "
                f"{_cell(values_of['success_rate'])}{marks['success_rate']} | "
                f"{_cell(values_of['training_danger'])}{marks['training_danger']} |")
    return lines


def scorecard_lines(found: dict[str, Any]) -> list[str]:
    """The scorecard extended to the Lagrangian (``found``: :func:`scorecard`'s), as a
    table: per comparison, the pairs where one variant is better (lower danger, higher
    success), how many significantly and how many after Holm."""

    def count(side: dict[str, int], of: int) -> str:
        return (f"{side['cells']} of {of} ({side['significant']} significantly, "
                f"{side['significant_holm']} after Holm)")

    lines = ["| over the 9 pairs | danger | success | danger in training |",
             "|---|---|---|---|"]
    rows = [(f"the Lagrangian better than {NAMES[base]}", base, "better") for base in BASELINES]
    rows.append(("CCR better than the Lagrangian", "ccr", "worse"))
    for label, base, side in rows:
        lines.append(f"| {label} | " + " | ".join(
            count(found[base][metric][side], found[base][metric]["of"])
            for metric in ("danger_frequency", "success_rate", "training_danger")) + " |")
    return lines


def markdown(result: dict[str, Any]) -> str:
    settings = result["settings"]
    limit = settings["cost_limit"]
    lines = ["# The constrained baseline beside plain, pessimistic and CCR", ""]
    if settings["quick"]:
        lines += [protocol.quick_note(), ""]
    lines += [
        f"Every variant at {settings['steps']:,} environment steps per run, the tables' seeds "
        f"{settings['seeds']}; the Lagrangian at cost limit **{limit:g}** "
        f"({result['sources'].get('cost_limit', 'given')}); the other variants are their runs in "
        f"{result['sources']['tables']} evaluated at this budget (docs/protocol.md, amendment "
        f"of 2026-12-02). Mean and 95% interval over seeds; `*` marks a Welch test of the "
        "Lagrangian against that variant with p < 0.05. Training danger: the share of "
        "robot-steps in danger from the start of learning to the budget.",
        "", "## The three searches' choices at this budget", "",
        "| searched | choice at this budget | the tables used |", "|---|---|---|"]
    for variant, chosen in result["selections_at_budget"].items():
        used = result["tables_values"].get(variant, {}).get(PARAMETERS[variant], ["-"])
        text = chosen.get("missing") or (f"{chosen['value']:g}" + (" (fallback)" if
                                                                   chosen["fallback"] else ""))
        lines.append(f"| {PARAMETERS[variant]} ({NAMES[variant]}) | {text} | "
                     f"{', '.join(f'{v:g}' if isinstance(v, float) else str(v) for v in used)} |")
    for key, row in result["pairs"].items():
        scenario, algo = key.split("-")
        met = sum(row["meets_limit"])
        in_training = sum(row.get("meets_limit_in_training", []))
        lines += ["", f"## {SCENARIO_NAMES[scenario]}, {LEARNER_NAMES[algo]}", "",
                  f"Lagrangian seeds meeting the limit (final evaluated danger at most "
                  f"{limit:g}): {met} of {len(row['meets_limit'])}; in training (the last "
                  f"interval's danger of the training episodes, what the multiplier "
                  f"regulates): {in_training} of {len(row['meets_limit'])}.", "",
                  "| variant | danger | success | training danger | training danger, last "
                  "interval |", "|---|---|---|---|---|"]
        for variant, values in row["variants"].items():
            marks = ({m: _mark(row["welch"][variant][m]) for m in row["welch"][variant]}
                     if variant in row["welch"] else {})
            lines.append(f"| {NAMES[variant]} | {_cell(values['danger_frequency'])}"
                         f"{marks.get('danger_frequency', '')} | "
                         f"{_cell(values['success_rate'])}{marks.get('success_rate', '')} | "
                         f"{_cell(values['training_danger'])}"
                         f"{marks.get('training_danger', '')} | "
                         f"{_cell(values['last_interval_danger'])} |")
    lines += rule_value_lines(result.get("at_rule_values"))
    lines += ["", "## Over the 9 pairs (rliable)", "",
              "| metric | " + " | ".join(NAMES[v] for v in (*BASELINES, "lagrangian"))
              + " | P(Lagrangian better than plain / pessimistic / CCR) | P(CCR better than "
              "Lagrangian) |", "|---|---|---|---|---|---|---|"]
    for metric, found in result["aggregates"].items():
        iqm_text = " | ".join(f"{found['iqm'][v]['iqm']:.1%}" for v in
                              (*BASELINES, "lagrangian"))
        improvement = found["probability_of_improvement"]
        over = " / ".join(f"{improvement[f'lagrangian_over_{b}']['probability']:.2f}"
                          for b in BASELINES)
        lines.append(f"| {metric.replace('_', ' ')} (IQM) | {iqm_text} | {over} | "
                     f"{improvement['ccr_over_lagrangian']['probability']:.2f} |")
    lines += ["", "## The scorecard, extended", "",
              "Better: lower danger, higher success; Welch p < 0.05 per pair, Holm over "
              "the 9 pairs of each comparison.", "", *scorecard_lines(result["scorecard"])]
    found = result["hypotheses"]
    lines += ["", "## The amendment's hypotheses", "",
              f"H-L1: plain's mean danger is above the limit in "
              f"{len(found['pairs_plain_above_limit'])} pairs; the Lagrangian meets it within "
              f"its seeds' spread in {found['limit_met_within_spread']} of them: "
              f"{'holds' if found['h_l1_holds'] else 'does not hold'}.",
              "H-L2 (against pessimistic, pairs with the difference significant): " + "; ".join(
                  f"{m.replace('_', ' ')}: lower in {v['significantly_lower']}, higher in "
                  f"{v['significantly_higher']}" for m, v in found["versus_pessimistic"].items())
              + ".", "", "Made at " + ", ".join(f"`{c}`" for c in result["commits"]) + " on "
              + ", ".join(result["devices"]) + "."]
    return "\n".join(lines) + "\n"


def results_section(folder: str, result: dict[str, Any]) -> list[str]:
    """The results report's section on the constrained baseline (``result``: a
    ``constrained.json`` in ``experiments/results/<folder>``)."""
    settings = result["settings"]
    chosen = result["selections_at_budget"]
    choices = "; ".join(
        f"{PARAMETERS[v]} {c['value']:g}" if "value" in c else f"{PARAMETERS[v]}: {c['missing']}"
        for v, c in chosen.items())
    danger = result["aggregates"]["danger_frequency"]
    success = result["aggregates"]["success_rate"]
    training = result["aggregates"]["training_danger"]
    found = result["hypotheses"]
    met = {key: f"{sum(row['meets_limit'])}/{len(row['meets_limit'])}"
           for key, row in result["pairs"].items()}
    lines = [f"## The constrained baseline (Lagrangian) at {settings['steps']:,} steps", "",
             f"[`{folder}/constrained.md`]({folder}/constrained.md) (docs/protocol.md, "
             "amendment of 2026-12-02): the Lagrangian at cost limit "
             f"{settings['cost_limit']:g} beside plain, pessimistic and CCR read at the same "
             f"budget from their 6M runs, the tables' seeds. The rule at this budget chose: "
             f"{choices}.", "",
             "| over the 9 pairs (IQM) | plain | pessimistic | CCR | Lagrangian |",
             "|---|---|---|---|---|"]
    for name, found_metric in (("danger", danger), ("success", success),
                               ("danger in training", training)):
        lines.append(f"| {name} | " + " | ".join(
            f"{found_metric['iqm'][v]['iqm']:.1%}" for v in (*BASELINES, "lagrangian")) + " |")
    lines += ["", *scorecard_lines(result["scorecard"])]
    improvement = danger["probability_of_improvement"]
    at_rule = result.get("at_rule_values") or {}
    if at_rule.get("values"):
        values = ", ".join(f"{PARAMETERS[v]} {x:g}" for v, x in at_rule["values"].items())
        lines += ["", f"The rule at this budget chose {values}, not the tables' values: "
                  + (f"their cells at this budget are in [`constrained.md`]"
                     f"({folder}/constrained.md)."
                     if not at_rule["missing"]
                     else f"their cells at this budget are not made yet ({at_rule['missing']}).")]
    lines += ["", f"P(the Lagrangian is less dangerous than pessimistic) = "
              f"{improvement['lagrangian_over_pessimistic']['probability']:.2f}; P(CCR less "
              f"dangerous than the Lagrangian) = "
              f"{improvement['ccr_over_lagrangian']['probability']:.2f}. Seeds meeting the "
              "limit per pair: " + ", ".join(f"{k} {v}" for k, v in met.items()) + ". H-L1 "
              f"{'holds' if found['h_l1_holds'] else 'does not hold'} "
              f"({found['limit_met_within_spread']} of "
              f"{len(found['pairs_plain_above_limit'])} pairs where plain is above the limit).",
              ""]
    return lines


def summary_lines(result: dict[str, Any] | None) -> list[str]:
    """The results report's summary bullet on the constrained baseline (``result``: a
    ``constrained.json``; none where it is not made yet)."""
    if not result:
        return []
    settings = result["settings"]
    iqm = {metric: found["iqm"] for metric, found in result["aggregates"].items()}
    used = result["tables_values"]
    found = result["hypotheses"]
    versus = found["versus_pessimistic"]["danger_frequency"]

    def row(metric: str) -> str:
        return (f"{iqm[metric]['lagrangian']['iqm']:.1%} against plain's "
                f"{iqm[metric]['plain']['iqm']:.1%}, CCR's {iqm[metric]['ccr']['iqm']:.1%} and "
                f"pessimistic's {iqm[metric]['pessimistic']['iqm']:.1%}")

    penalty = ", ".join(f"{v:g}" for v in used["pessimistic"]["penalty"])
    lam = ", ".join(f"{v:g}" for v in used["ccr"]["lam"])
    return [
        f"* **The Lagrangian at {settings['steps'] / 1e6:g}M steps** (cost limit "
        f"{settings['cost_limit']:g}, {len(settings['seeds'])} seeds per cell; the tables' "
        f"penalty {penalty} and lambda {lam} read at the same budget; IQM over the 9 pairs): "
        f"danger {row('danger_frequency')}; success {row('success_rate')}; danger in "
        f"training {row('training_danger')}. Where plain is above the limit "
        f"({len(found['pairs_plain_above_limit'])} pairs) the Lagrangian meets it within its "
        f"seeds' spread in {found['limit_met_within_spread']}; the penalty is significantly "
        f"less dangerous than the Lagrangian in {versus['significantly_higher']} of 9 pairs, "
        f"CCR in {result['scorecard']['ccr']['danger_frequency']['worse']['significant']}."]
