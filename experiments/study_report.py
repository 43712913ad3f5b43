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

from ccrjax import cli
from ccrjax.run.folder import write_atomic
from ccrjax.run.stats import format_mean_ci
from ccrjax.viz.plots import PALETTE, save_figure
from experiments import protocol
from experiments.ledger import read_json
from experiments.study import VARIANTS
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


def effect(cells: Cells, regime: str, scenario: str, algo: str, variant: str, metric: str
           ) -> dict[str, float] | None:
    """A variant's effect against plain on ``metric`` in one cell of the grid, signed so
    that better is positive (less danger, more success), with the 95% interval of a
    difference of two means (normal, unequal variances, over seeds); ``None`` if either
    cell is missing."""
    mine, plain = (cells.get((regime, scenario, algo, v)) for v in (variant, "plain"))
    if mine is None or plain is None:
        return None
    a, b = per_seed(mine, metric), per_seed(plain, metric)
    difference = EFFECT_METRICS[metric] * float(a.mean() - b.mean())
    half = 1.96 * math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
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


def report(cells: Cells, resamples: int = 2000) -> tuple[dict[str, Any], str]:
    """``study.json``'s content and ``study.md``'s text over ``cells`` of both regimes."""
    pairs = sorted({(s, a) for _, s, a, _ in cells})
    result: dict[str, Any] = {
        "hypotheses": {f"{s}-{a}": hypotheses(cells, s, a, resamples) for s, a in pairs},
        "aggregates": {r: aggregates(cells, r, resamples) for r in REGIMES},
        "rows": {"/".join(k): cell_row(c) for k, c in sorted(cells.items())},
    }
    quick = any(c["settings"].get("quick") for c in cells.values())
    lines = ["# The study: CCR's premise in two regimes", "",
             *([protocol.quick_note(regime=max(
                 {k[0] for k in cells}, key=lambda r: protocol.REGIMES[r].quick_episode_length)),
                ""] if quick else []),
             "docs/protocol.md, amendment of 2026-12-01 (the study) and its addition. Mean and "
             "Student-t 95% interval over seeds; the forewarned share counts the dangerous "
             "robot-steps a teammate in range forewarned 2 or more steps ahead; the followers "
             "are every robot but the one starting furthest along the way.", ""]
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
        lines.append("")
    lines += ["## Over the study's pairs", ""]
    for regime, found in result["aggregates"].items():
        if not found["pairs"]:
            continue
        iqms = found["iqm"]["danger_frequency"]
        safer = found["ccr_safer_than_plain"]
        lines.append(
            f"* `{regime}` ({', '.join(found['pairs'])}): interquartile mean of danger "
            + ", ".join(f"{v} {x['iqm']:.1%} [{x['ci_low']:.1%}, {x['ci_high']:.1%}]"
                        for v, x in sorted(iqms.items(), key=lambda i: VARIANTS.index(i[0])))
            + ("" if safer is None else
               f"; P(a CCR run is safer than a plain one) {safer['probability']:.2f} "
               f"[{safer['ci_low']:.2f}, {safer['ci_high']:.2f}]"))
    lines += ["", "## Hypotheses", ""]
    for name, found in result["hypotheses"].items():
        lines += [f"### {name}", "",
                  f"* H1 (today: CCR's danger is plain's): {verdict(found['H1'])}"
                  + (f", p = {found['H1']['p']:.3f}" if "p" in found["H1"] else ""),
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
    return result, "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True,
                        help="where study.md, study.json and effects.png are written")
    for regime in REGIMES:
        parser.add_argument(f"--{regime}", type=Path, default=None,
                            help=f"the {regime} regime's study folder (default: <out>/{regime})")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cells: Cells = {}
    for regime in REGIMES:
        cells.update(read_cells(getattr(args, regime) or args.out / regime, regime))
    if not cells:
        cli.fail(PROG, f"no study cells in {args.out}/today or {args.out}/column (or the "
                 "folders given): run experiments/study.py first")
    quick = any(c["settings"].get("quick") for c in cells.values())
    result, markdown = report(cells, resamples=200 if quick else 2000)
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
