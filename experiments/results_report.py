"""The results report, ``experiments/results/README.md``, written from the committed results.

    python -m experiments.results_report            # write it from experiments/results
    python -m experiments.results_report --check    # exit 1 if the committed one differs

Every number comes from a result file (``tables*/tables.json``, ``search*/<variant>/
search.json``, ``*budget*/budgets.json``, ``regimes/regimes.json``) or from the paper's
tables (:mod:`experiments.paper`); the text around them says what we think they show. The
same files give the same report, byte for byte, so ``experiments/tables.py`` rewrites it
whenever it writes its tables into ``experiments/results/``, and a test checks that the
committed report is the one these files give. A result folder that is missing is left out.
"""

from __future__ import annotations

# ruff: noqa: E402 - the stop handling is installed before the other imports
from ccrjax import terminal

if __name__ == "__main__":  # a command: Ctrl-C and SIGTERM are answered from here on
    terminal.install("python -m experiments.results_report")

import sys
from pathlib import Path

from ccrjax import cli
from ccrjax.run.folder import write_atomic
from experiments.constrained_report import results_section
from experiments.constrained_report import summary_lines as constrained_summary
from experiments.ledger import RESULTS, read_json
from experiments.results_on_policy import SEARCHES as ON_POLICY_SEARCHES
from experiments.results_on_policy import TABLES as ON_POLICY_TABLES
from experiments.results_on_policy import on_policy_section
from experiments.results_on_policy import summary_lines as on_policy_summary
from experiments.results_sections import (
    STATIC_EXPLANATIONS,
    budgets_section,
    explanations,
    plain_section,
    regimes_section,
    scorecard,
    searches_section,
    summary_section,
    tables_section,
)

PROG = "python -m experiments.results_report"
TABLES = (("tables", "3M"), ("tables_6m", "6M"))  # folder, budget label
SEARCHES = (("search", "3M"), ("search_6m", "6M"))
LAGRANGIAN_SEARCH = ("search_lagrangian", "2M")  # its amendment's budget
CONSTRAINED = "constrained"  # experiments/constrained.py's folder
BUDGETS = (("budgets", "the budget seeds 200-202"), ("longer_budget", "the tables' seeds"),
           ("budgets_on_policy", "the budget seeds 200-202 (the on-policy learners)"),
           ("study/budgets_column", "the budget seeds 200-202 (the study's column regime)"))


def report(results: Path = RESULTS) -> str:
    """The report's text from the result files under ``results``."""
    tables = {label: r for folder, label in TABLES
              if (r := read_json(results / folder / "tables.json"))}
    searches = {label: found for folder, label in SEARCHES
                if (found := {v: s for v in ("ccr", "pessimistic")
                              if (s := read_json(results / folder / v / "search.json"))})}
    folder, label = LAGRANGIAN_SEARCH
    if lagrangian := read_json(results / folder / "search.json"):
        searches = {label: {"lagrangian": lagrangian}, **searches}
    budgets = {folder: (what, r) for folder, what in BUDGETS
               if (r := read_json(results / folder / "budgets.json"))}
    regimes = read_json(results / "regimes" / "regimes.json")
    constrained = read_json(results / CONSTRAINED / "constrained.json")
    on_policy_searches = {v: s for v in ("ccr", "pessimistic")
                          if (s := read_json(results / ON_POLICY_SEARCHES / v / "search.json"))}
    on_policy_tables = read_json(results / ON_POLICY_TABLES / "tables.json")
    lines = [
        "# Results", "",
        "What ccrjax has measured: the paper's Tables I and II re-run under the "
        "preregistered protocol ([`docs/protocol.md`](../../docs/protocol.md)), the searches "
        "of CCR's lambda, the pessimistic penalty and the Lagrangian's cost limit, the "
        "budgets and the information regimes. This page is written by "
        "`python -m experiments.results_report` (and by "
        "`experiments/tables.py` when it writes here) from the result files it links to; "
        "each cell's file names its command, commit and device. The manual is the top-level "
        "[`README.md`](../../README.md); how the experiments run and resume: "
        "[`docs/experiments.md`](../../docs/experiments.md).", "",
    ]
    summary = summary_section(tables, searches)
    lines += (summary[:-1] + constrained_summary(constrained) + on_policy_summary(on_policy_tables)
              + summary[-1:])
    if tables:
        lines += ["## The claims, counted as the paper makes them", "", *scorecard(tables)]
    for folder, label in TABLES:
        if label in tables:
            lines += tables_section(folder, label, tables[label])
    if searches:
        lines += searches_section(searches)
    if constrained:
        lines += results_section(CONSTRAINED, constrained)
    if on_policy_searches or on_policy_tables:
        lines += on_policy_section(on_policy_searches, on_policy_tables)
    if tables:
        lines += plain_section(tables)
    if budgets:
        lines += budgets_section(budgets)
    if regimes:
        lines += regimes_section(regimes)
    lines += ["## What we think explains each disagreement", "", *explanations(tables),
              *STATIC_EXPLANATIONS]
    return "\n".join(lines).rstrip("\n") + "\n"


def write_report(results: Path = RESULTS) -> Path:
    path = results / "README.md"
    write_atomic(path, report(results))
    return path


def build_parser() -> cli.Parser:
    parser = cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--results", type=Path, default=RESULTS,
                        help="the results folder (default: experiments/results)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 if the folder's README.md is not the "
                        "report its files give")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.results.is_dir():
        parser.error(f"--results: {args.results} is not a folder")
    if args.check:
        path = args.results / "README.md"
        current = path.read_text() if path.exists() else None
        if current != report(args.results):
            print(f"{path} is not the report its result files give: run {PROG}",
                  file=sys.stderr)
            return 1
        print(f"{path} is up to date")
        return 0
    print(f"wrote {write_report(args.results)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(terminal.run_command(PROG, main, "nothing to keep"))
