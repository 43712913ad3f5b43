"""The study's report: ``python experiments/study_report.py``.

    python experiments/study_report.py --out experiments/results/study
    python experiments/study_report.py --today /tmp/s/today --column /tmp/s/column --out /tmp/s

Reads the cells that ``experiments/study.py`` made in each regime's folder (``--today``,
``--column``; default ``<out>/today`` and ``<out>/column``), and writes ``study.md`` and
``study.json`` (per regime a table of the cells with the study's measures, per scenario and
learner the amendment's hypotheses H1 to H5 from :mod:`experiments.study_analysis`, the
aggregates over the study's pairs) and ``effects.png``: per scenario, every variant's effect
on danger and on success against plain (plain's danger minus the variant's; the variant's
success minus plain's) in both regimes, with 95% intervals. What no cell is made for yet is
said, never filled in. Anything beyond the amendment's analysis is marked exploratory.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python experiments/study_report.py")

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import stats as scipy_stats

from ccrjax import cli
from ccrjax.run.folder import write_atomic
from ccrjax.run.stats import format_mean_ci
from ccrjax.run.sweep_grid import nonfinite_runs, nonfinite_text
from ccrjax.viz.plots import PALETTE, save_figure
from experiments import protocol, study
from experiments.cell_identity import settings_record, why_not_current
from experiments.ledger import read_json
from experiments.study import PROGRAMS, STUDY_SEEDS, VARIANTS
from experiments.study_analysis import Cells, aggregates, cell_row, hypotheses, per_seed

PROG = "python experiments/study_report.py"
REGIMES = ("today", "column")
EFFECT_METRICS = {"danger_frequency": -1.0, "success_rate": 1.0}  # sign: better is > 0


def read_cells(folder: Path, regime: str) -> Cells:
    """The cells of ``folder`` made by ``experiments/study.py`` in ``regime`` (its
    ``study_cells.json`` names the programs made), keyed ``(regime, scenario, algo,
    variant)``; none if the folder holds no study."""
    if not (folder / "study_cells.json").is_file():
        return {}
    cells = {}
    for path in sorted((folder / "cells").glob("*.json")):
        cell = read_json(path)
        if not cell or cell.get("settings", {}).get("regime", "today") != regime:
            continue
        cells[(regime, cell["scenario"], cell["algo"], cell["variant"])] = cell
    return cells


def program_of(variant: str) -> tuple[str, ...]:
    return next(program for program in PROGRAMS if variant in program)


def trimmed(cell: dict[str, Any], seeds: int) -> dict[str, Any]:
    """``cell`` with its per-seed values of the first ``seeds`` seeds only."""
    def cut(values: dict[str, list]) -> dict[str, list]:
        return {k: list(v)[:seeds] for k, v in values.items()}

    return {**cell, "seeds": cell["seeds"][:seeds], "final": cut(cell["final"]),
            "measures": cut(cell.get("measures", {}))}


def protocol_cells(cells: Cells, searches: dict[str, Path]
                   ) -> tuple[Cells, Cells, dict[str, dict[str, str]], list[str]]:
    """The cells the protocol's study would make now, each with the value the regime's
    search chose for its variant (``searches[regime]``, as ``experiments/study.py``
    finds it), on the tables' seeds from 0: trimmed to the study's seeds 0-4 (the
    analysis the addition of 2026-12-03 states), and whole (every seed made); per regime
    each value and where it came from; and a line per cell left out, saying why (its
    search not finished, a value given by hand, other settings, other seeds)."""
    primary: Cells = {}
    whole: Cells = {}
    values: dict[str, dict[str, str]] = {}
    left_out: list[str] = []
    expected: dict[tuple, dict[str, Any] | str] = {}
    for key, cell in sorted(cells.items()):
        regime, scenario, algo, variant = key
        name = f"{regime}: {scenario}-{algo}-{variant}"
        program = program_of(variant)
        quick = bool(cell["settings"].get("quick"))
        seeds = list(cell.get("seeds", []))
        if not quick and (len(seeds) < STUDY_SEEDS or seeds != list(range(len(seeds)))):
            left_out.append(f"{name}: seeds {seeds}, not the tables' from 0 (at least "
                            f"{STUDY_SEEDS})")
            continue
        wanted = (regime, program, len(seeds), quick, algo)
        if wanted not in expected:
            argv = ["--regime", regime, "--variants", *program, "--algos", algo,
                    "--searches", str(searches[regime])]
            argv += ["--quick"] if quick else ["--seeds", str(len(seeds))]
            try:
                settings, sources = study.settings_from(study.build_parser().parse_args(argv))
            except cli.UsageError as error:
                expected[wanted] = str(error)
            else:
                expected[wanted] = settings_record(settings.for_program(program))
                for v, x in settings.values.items():
                    values.setdefault(regime, {})[v] = f"{x:g} ({sources[v]})"
        record = expected[wanted]
        why = record if isinstance(record, str) else why_not_current(cell, record)
        if why is not None:
            left_out.append(f"{name}: {why}")
            continue
        whole[key] = cell
        primary[key] = cell if quick else trimmed(cell, STUDY_SEEDS)
    return primary, whole, values, left_out


def effect(cells: Cells, regime: str, scenario: str, algo: str, variant: str, metric: str
           ) -> dict[str, float] | None:
    """A variant's effect against plain on ``metric`` in one cell of the grid, signed so
    that better is positive (less danger, more success), with the 95% interval of a
    difference of two means (Welch's: Student-t with the Welch-Satterthwaite degrees of
    freedom, over seeds); ``None`` if either cell is missing."""
    mine, plain = (cells.get((regime, scenario, algo, v)) for v in (variant, "plain"))
    if mine is None or plain is None:
        return None
    a, b = per_seed(mine, metric), per_seed(plain, metric)
    difference = EFFECT_METRICS[metric] * float(a.mean() - b.mean())
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    if va + vb == 0.0:
        return {"effect": difference, "ci_low": difference, "ci_high": difference}
    dof = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
    half = float(scipy_stats.t.ppf(0.975, dof)) * math.sqrt(va + vb)
    return {"effect": difference, "ci_low": difference - half, "ci_high": difference + half}


def draw_effects(cells: Cells, path: Path, quick: bool) -> None:
    """``effects.png``: a row per scenario and learner, a column per metric; for every
    variant but plain a bar per regime (:func:`effect`)."""
    pairs = sorted({(s, a) for _, s, a, _ in cells})
    variants = [v for v in VARIANTS if v != "plain" and any(k[3] == v for k in cells)]
    fig = Figure(figsize=(9.0, 2.8 * max(1, len(pairs))), dpi=120)
    FigureCanvasAgg(fig)
    for row, (scenario, algo) in enumerate(pairs):
        for column, metric in enumerate(EFFECT_METRICS):
            ax = fig.add_subplot(max(1, len(pairs)), 2, 2 * row + column + 1)
            for index, regime in enumerate(REGIMES):
                found = [effect(cells, regime, scenario, algo, v, metric) for v in variants]
                x = np.arange(len(variants)) + (index - 0.5) * 0.4
                shown = [(i, e) for i, e in zip(x, found, strict=True) if e is not None]
                if not shown:
                    continue
                xs, es = zip(*shown, strict=True)
                ax.bar(xs, [e["effect"] for e in es], width=0.4, color=PALETTE[index],
                       yerr=[[e["effect"] - e["ci_low"] for e in es],
                             [e["ci_high"] - e["effect"] for e in es]], capsize=2,
                       label=regime)
            ax.axhline(0.0, color="black", linewidth=0.6)
            ax.set_xticks(np.arange(len(variants)))
            ax.set_xticklabels(variants, rotation=30, ha="right", fontsize=7)
            what = "plain's danger - variant's" if metric == "danger_frequency" else (
                "variant's success - plain's")
            ax.set_title(f"{scenario}, {protocol.LEARNER_NAMES.get(algo, algo)}: {what}",
                         fontsize=8)
            ax.grid(axis="y", alpha=0.3)
            if row == 0 and column == 0:
                ax.legend(fontsize=7)
    fig.suptitle(f"{protocol.QUICK_FIGURE if quick else ''}the study: each variant's effect "
                 "against plain (95% intervals over seeds)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def _pct(stats: dict[str, Any] | None, percent: bool = True) -> str:
    return "not measured" if stats is None else format_mean_ci(stats, percent, digits=1)


def verdict(entry: dict[str, Any]) -> str:
    """A hypothesis' verdict in words."""
    return {None: "not yet (cells missing)", True: "**holds**", False: "does not hold"}[
        entry.get("holds")]


def regime_notes(cells: Cells, regime: str, values: dict[str, str]) -> list[str]:
    """What a regime's cells were made with: each variant's value and where it came from,
    the budget, whether plain's return levelled off, the runs whose updates went non-finite."""
    own = {k: c for k, c in cells.items() if k[0] == regime}
    budgets = sorted({c["budget"] for c in own.values() if "budget" in c})
    levelled = [f"{s}-{a} {protocol.PLATEAU_WORDS[c['return_plateau']['plateaued']]}"
                for (_, s, a, v), c in sorted(own.items())
                if v == "plain" and isinstance(c.get("return_plateau"), dict)]
    skipped = [line for (_, s, a, v), c in sorted(own.items())
               for line in nonfinite_runs(c, f"{s}, {a}, {v}")]
    runs = sum(len(c["seeds"]) for c in own.values())
    return [
        "Values: " + ("; ".join(f"{v} {text}" for v, text in values.get(regime, {}).items())
                      or "none searched") + ".",
        "Budget: " + (", ".join(f"{b:,}" for b in budgets) or "none") + " steps per run"
        + ("" if regime == protocol.DEFAULT_REGIME or regime not in protocol.REGIME_BUDGETS
           or protocol.REGIME_BUDGETS[regime] else
           " (the regime's budget is not chosen yet: its largest candidate)") + ".",
        "Plain's return levelled off at the budget (the tables' plateau check): "
        + (", ".join(levelled) or "no plain cell") + ".",
        nonfinite_text(skipped, f"the {runs} runs"), "",
    ]


def hypothesis_lines(found_by_pair: dict[str, dict[str, Any]]) -> list[str]:
    """Each pair's H1 to H5 in words, with their statistics."""
    lines = []
    for name, found in found_by_pair.items():
        h1 = found["H1"]
        lines += [f"### {name}", "",
                  f"* H1 (today: CCR's danger is plain's): {verdict(h1)}"
                  + (f", CCR's danger {h1['difference']:+.1%} against plain's, p = "
                     f"{h1['p']:.3f} (with so few seeds, no difference found is not "
                     "equality)" if "p" in h1 else ""),
                  f"* H2 (column: CCR's danger below plain's, success within 5 points): "
                  f"{verdict(found['H2'])}"
                  + (f", one-sided p = {found['H2']['p']:.3f}, success "
                     f"{0.0 - found['H2']['success_drop']:+.1%}" if "p" in found["H2"] else ""),
                  f"* H3 (CCR's effect larger in the column): {verdict(found['H3'])}"
                  + (f", {found['H3']['difference']:+.1%} [{found['H3']['ci_low']:+.1%}, "
                     f"{found['H3']['ci_high']:+.1%}]" if "difference" in found["H3"] else "")]
        for label, tests in found["H4"].items():
            parts = [f"against {who}: {test['difference']:+.1%} (p = {test['p']:.3f})"
                     for who, test in (("plain", tests["against_plain"]),
                                       ("CCR", tests["against_ccr"])) if test is not None]
            lines.append(f"* H4 {label}, danger " + "; ".join(parts))
        for label, tests in found["H5"].items():
            lines.append(f"* H5 CCR against {label}: danger "
                         f"{tests['danger_frequency']['difference']:+.1%} (p = "
                         f"{tests['danger_frequency']['p']:.3f}), success "
                         f"{tests['success_rate']['difference']:+.1%} (p = "
                         f"{tests['success_rate']['p']:.3f})")
        lines.append("")
    return lines


def report(cells: Cells, resamples: int = 2000, whole: Cells | None = None,
           values: dict[str, dict[str, str]] | None = None,
           left_out: list[str] | None = None) -> tuple[dict[str, Any], str]:
    """``study.json``'s content and ``study.md``'s text over ``cells`` of both regimes (the
    primary analysis: :func:`protocol_cells`' trimmed cells); ``whole``, the same cells
    with every seed made, adds the analysis on all of them beside it where any cell holds
    more than the study's seeds; ``values`` and ``left_out`` are said."""
    pairs = sorted({(s, a) for _, s, a, _ in cells})
    result: dict[str, Any] = {
        "hypotheses": {f"{s}-{a}": hypotheses(cells, s, a, resamples) for s, a in pairs},
        "aggregates": {r: aggregates(cells, r, resamples) for r in REGIMES},
        "rows": {"/".join(k): cell_row(c) for k, c in sorted(cells.items())},
        "values": values or {}, "left_out": left_out or [],
    }
    quick = any(c["settings"].get("quick") for c in cells.values())
    lines = ["# The study: CCR's premise in two regimes", "",
             *([protocol.quick_note(regime=max(
                 {k[0] for k in cells}, key=lambda r: protocol.REGIMES[r].quick_episode_length)),
                ""] if quick else []),
             "docs/protocol.md, amendment of 2026-12-01 (the study) and its additions. Mean and "
             "Student-t 95% interval over the study's seeds 0-4 (the addition of 2026-12-03); "
             "the forewarned share counts the dangerous robot-steps a teammate in range "
             "forewarned 2 or more steps ahead; the followers are every robot but the one "
             "starting furthest along the way.", ""]
    for regime in REGIMES:
        own = {k: c for k, c in cells.items() if k[0] == regime}
        lines += [f"## Regime `{regime}`", ""]
        if not own:
            lines += ["No cell is made yet.", ""]
            continue
        lines += ["| scenario | learner | variant | danger | success | forewarned share | "
                  "followers: distance to centre | followers: danger | followers: success | "
                  "seeds |", "|---|---|---|---|---|---|---|---|---|---|"]
        for (_, scenario, algo, variant), cell in sorted(
                own.items(), key=lambda kv: (kv[0][1], kv[0][2], VARIANTS.index(kv[0][3]))):
            row = cell_row(cell)
            lines.append(
                f"| {scenario} | {protocol.LEARNER_NAMES.get(algo, algo)} | {variant} | "
                f"{_pct(row['danger_frequency'])} | {_pct(row['success_rate'])} | "
                f"{_pct(row['forewarned_share'])} | "
                f"{_pct(row['followers_centre_distance'], False)} | "
                f"{_pct(row['followers_danger'])} | {_pct(row['followers_success'])} | "
                f"{len(cell['seeds'])} |")
        lines += ["", *regime_notes(cells, regime, values or {})]
    if left_out:
        lines += ["Left out (not what the protocol's study would make now):", "",
                  *(f"* {line}" for line in left_out), ""]
    lines += ["## Over the study's pairs", ""]
    for regime, found in result["aggregates"].items():
        if not found["pairs"]:
            continue
        safer = found["ccr_safer_than_plain"]
        lines.append(
            f"* `{regime}` ({', '.join(found['pairs'])}): interquartile mean of "
            + "; of ".join(
                name + " " + ", ".join(
                    f"{v} {x['iqm']:.1%} [{x['ci_low']:.1%}, {x['ci_high']:.1%}]"
                    for v, x in sorted(found["iqm"][metric].items(),
                                       key=lambda i: VARIANTS.index(i[0])))
                for metric, name in (("danger_frequency", "danger"),
                                     ("success_rate", "success")))
            + ("" if safer is None else
               f"; P(a CCR run is safer than a plain one) {safer['probability']:.2f} "
               f"[{safer['ci_low']:.2f}, {safer['ci_high']:.2f}]"))
    lines += ["", "## Hypotheses", "", *hypothesis_lines(result["hypotheses"])]
    if whole is not None and any(len(c["seeds"]) > STUDY_SEEDS for c in whole.values()):
        counts = {len(c["seeds"]) for c in whole.values()}
        lines += ["## Hypotheses on every seed made (beside the analysis above)", ""]
        if len(counts) > 1:
            lines += [f"Not made: the cells hold {sorted(counts)} seeds; this analysis "
                      "waits until every cell holds the same seeds.", ""]
        else:
            result["hypotheses_every_seed"] = {
                f"{s}-{a}": hypotheses(whole, s, a, resamples) for s, a in pairs}
            lines += hypothesis_lines(result["hypotheses_every_seed"])
    return result, "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True,
                        help="where study.md, study.json and effects.png are written")
    for regime in REGIMES:
        parser.add_argument(f"--{regime}", type=Path, default=None,
                            help=f"the {regime} regime's study folder, its searches in its "
                        f"search/ (default: <out>/{regime})")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cells: Cells = {}
    folders = {regime: getattr(args, regime) or args.out / regime for regime in REGIMES}
    for regime, folder in folders.items():
        cells.update(read_cells(folder, regime))
    if not cells:
        cli.fail(PROG, f"no study cells in {args.out}/today or {args.out}/column (or the "
                 "folders given): run experiments/study.py first")
    primary, whole, values, left_out = protocol_cells(
        cells, {regime: folder / "search" for regime, folder in folders.items()})
    quick = any(c["settings"].get("quick") for c in cells.values())
    result, markdown = report(primary, 200 if quick else 2000, whole, values, left_out)
    try:
        cli.make_folder(args.out)
    except cli.UsageError as error:
        cli.fail(PROG, str(error))
    write_atomic(args.out / "study.json", json.dumps(result, indent=1) + "\n")
    write_atomic(args.out / "study.md", markdown)
    draw_effects(cells, args.out / "effects.png", quick)
    print(markdown)
    print(f"wrote {args.out / 'study.md'}, study.json, effects.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, "nothing: the report's files are "
                                          "written whole or not at all"))
