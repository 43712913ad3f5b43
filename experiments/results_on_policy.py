"""The results report's section on the on-policy learners (IPPO, MAPPO), a family of their
own under the amendment of 2026-12-02 (``docs/protocol.md``): their searches of lambda and
the penalty over their 6 pairs, their tables beside the paper's learners', and the
amendment's two hypotheses counted pair by pair:

* **H-P1**: CCR lowers the learner's danger against plain (Welch, p < 0.05) at a mean
  success at most 5 points below plain's;
* **H-P2**: CCR's danger is no lower than the tuned penalty's (not significantly below it).

What is not made yet is said, with the command that makes it.
"""

from __future__ import annotations

from typing import Any

from experiments import protocol
from experiments.paper import PAPER_SCENARIOS
from experiments.results_sections import (
    interval,
    pair_name,
    pair_table,
    pct,
    records_of,
    rliable_text,
    search_rows,
    span,
)

FAMILY = protocol.ON_POLICY_ALGOS
PAIRS = [(scenario, algo) for scenario in PAPER_SCENARIOS for algo in FAMILY]
SEARCHES = "search_on_policy"  # the searches' folder under experiments/results
TABLES = "tables_on_policy"  # the tables' folder
PARAMETERS = {"ccr": "lambda", "pessimistic": "penalty"}
SUCCESS_MARGIN = 0.05  # H-P1: CCR's success at most this below plain's


def search_command(variant: str) -> str:
    return (f"python experiments/search.py --variant {variant} --algos ippo mappo --out "
            f"experiments/results/{SEARCHES}/{variant} --force")


TABLES_COMMAND = (f"python experiments/tables.py --algos ippo mappo --out "
                  f"experiments/results/{TABLES} --force")


def hypotheses(result: dict[str, Any]) -> dict[str, Any]:
    """H-P1 and H-P2 per pair of the on-policy tables' ``result`` (``tables.json``), and
    how many of the 6 pairs each holds in."""
    by_key = records_of(result)
    pairs = []
    for scenario, algo in PAIRS:
        ccr, plain = by_key[(scenario, algo, "ccr")], by_key[(scenario, algo, "plain")]
        welch = ccr["danger_frequency"]["welch"]
        success_drop = plain["success_rate"]["mean"] - ccr["success_rate"]["mean"]
        below_plain = welch["plain"]["significant"] and welch["plain"]["difference"] < 0
        below_penalty = (welch["pessimistic"]["significant"]
                         and welch["pessimistic"]["difference"] < 0)
        pairs.append({"scenario": scenario, "algo": algo,
                      "danger_below_plain": bool(below_plain),
                      "success_drop": float(success_drop),
                      "H-P1": bool(below_plain and success_drop <= SUCCESS_MARGIN),
                      "H-P2": not below_penalty})
    return {"pairs": pairs, **{h: sum(p[h] for p in pairs) for h in ("H-P1", "H-P2")}}


def search_lines(searches: dict[str, dict[str, Any]]) -> list[str]:
    """Each search's values with the chosen one in bold, or the command that makes it."""
    lines = []
    for variant, name in PARAMETERS.items():
        search = searches.get(variant)
        if search is None:
            lines.append(f"* {name}: not made yet (`{search_command(variant)}`).")
            continue
        chosen = search["selection"]["value"]
        cells = [(f"**{value:g}**" if value == chosen else f"{value:g}")
                 + f": {pct(d)} / {pct(s)}" for value, (d, s) in search_rows(search).items()]
        provisional = ("" if search["selection"].get("protocol", True) else
                       f" (provisional: {search['selection']['provisional_because']})")
        lines.append(f"* {name}: " + "; ".join(cells) + f"{provisional}.")
    return lines


def hypothesis_lines(result: dict[str, Any]) -> list[str]:
    found = hypotheses(result)

    def which(key: str) -> str:
        held = [pair_name(p["scenario"], p["algo"]) for p in found["pairs"] if p[key]]
        return f" ({'; '.join(held)})" if held else ""

    return [
        f"* H-P1, CCR lowers the danger of an on-policy learner against plain (Welch, p < "
        f"0.05) at a success at most {100 * SUCCESS_MARGIN:g} points below: holds in "
        f"{found['H-P1']} of {len(PAIRS)} pairs{which('H-P1')}.",
        f"* H-P2, CCR's danger is no lower than the tuned penalty's: holds in "
        f"{found['H-P2']} of {len(PAIRS)} pairs.",
    ]


def summary_lines(tables: dict[str, Any] | None) -> list[str]:
    """The summary's bullet on the on-policy tables (none before they are made): CCR
    against plain and against the tuned penalty over the family's pairs, and the
    amendment's two hypotheses."""
    if tables is None:
        return []
    found, by_key = hypotheses(tables), records_of(tables)
    plain = tables["claims"]["danger_lower_vs_plain"]
    better = tables["aggregates"]["danger_frequency"]["probability_of_improvement"]
    danger = {v: [by_key[(s, a, v)]["danger_frequency"]["mean"] for s, a in PAIRS]
              for v in ("pessimistic", "ccr")}
    held = [pair_name(p["scenario"], p["algo"]) for p in found["pairs"] if p["H-P1"]]
    settings = tables["settings"]
    return [
        f"* **The on-policy learners** (IPPO and MAPPO, "
        f"{protocol.ON_POLICY_BUDGET / 1e6:g}M steps, lambda {settings['lam']:g}, penalty "
        f"{settings['penalty']:g}, {len(settings['seeds'])} seeds per cell): CCR's danger is "
        f"below plain's in {plain['cells']} of {len(PAIRS)} pairs ({plain['significant']} "
        f"significantly, {plain['significant_holm']} after Holm); the danger reduction "
        f"against plain is {interval(tables['headlines']['danger_reduction_vs_plain'])} and "
        f"the probability that a CCR run is safer than a plain one "
        f"{better['plain']['probability']:.2f}. H-P1 (lower danger at most "
        f"{100 * SUCCESS_MARGIN:g} points of success below plain's) holds in {found['H-P1']} "
        f"of {len(PAIRS)}" + (f" ({'; '.join(held)})" if held else "") + "; H-P2 (no lower "
        f"than the tuned penalty's) in {found['H-P2']} of {len(PAIRS)}: the penalty is in "
        f"danger {span(danger['pessimistic'])} of the time against CCR's "
        f"{span(danger['ccr'])}.",
    ]


def on_policy_section(searches: dict[str, dict[str, Any]], tables: dict[str, Any] | None
                      ) -> list[str]:
    """The section: the searches (``search.json`` by variant, those made) and the tables
    (``tables.json``, or ``None`` if not made yet)."""
    lines = [
        "## The on-policy learners", "",
        "IPPO and MAPPO ([`docs/learners.md`](../../docs/learners.md)) are a family of their "
        "own (the amendment of 2026-12-02 in [`docs/protocol.md`](../../docs/protocol.md)): "
        f"their budget, {protocol.ON_POLICY_BUDGET / 1e6:g}M steps, was chosen on their plain "
        f"learners alone; lambda and the penalty are searched alike over their {len(PAIRS)} "
        "pairs on the selection seeds 100-102 by the protocol's rule; their tables stand "
        "beside the paper's learners', not pooled with them. The searches, danger / success "
        f"in %, averaged over pairs and seeds ([`{SEARCHES}/`]({SEARCHES}/)):", "",
        *search_lines(searches), "",
    ]
    if tables is None:
        return lines + [f"Their tables are not made yet (`{TABLES_COMMAND}`).", ""]
    settings, seeds = tables["settings"], tables["settings"]["seeds"]
    return lines + [
        f"Their tables, {len(seeds)} seeds per cell (seeds {seeds[0]}-{seeds[-1]}) of plain, "
        f"pessimistic (penalty {settings['penalty']:g}) and CCR (lambda {settings['lam']:g}), "
        f"made on {', '.join(tables['devices'])}: [`{TABLES}/tables.md`]({TABLES}/tables.md). "
        "The final evaluation, mean over seeds in %, marked as in the paper's tables above:",
        "", *pair_table(tables, PAIRS, paper=False), rliable_text(tables, len(PAIRS)), "",
        "The amendment's hypotheses, per pair:", "", *hypothesis_lines(tables), "",
    ]
