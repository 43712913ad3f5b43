"""The sections of the results report (:mod:`experiments.results_report`), each a list of
Markdown lines written from result files: the tables beside the paper's, the scorecard,
the searches, the plain learners, the budgets, the regimes, and what we think explains each
disagreement."""

from __future__ import annotations

import math
from typing import Any

from ccrjax.training import ALGOS
from experiments.budgets_report import on_policy_lines
from experiments.paper import PAPER, PAPER_HEADLINES, PAPER_SCENARIOS
from experiments.regimes import chosen_regime_lines
from experiments.tables_grid import LEARNER_NAMES, SCENARIO_NAMES, VARIANTS
from experiments.tables_report import welch_symbols

PAIRS = [(s, a) for s in PAPER_SCENARIOS for a in ALGOS]


def pct(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None else f"{100 * value:.{digits}f}"


def interval(value: dict[str, Any], key: str = "mean", signed: bool = False) -> str:
    """``m% [low, high]`` from a record with ``key``, ``ci_low`` and ``ci_high``."""
    sign = "+" if signed else ""
    if value.get(key) is None:
        return "n/a"
    text = f"{100 * value[key]:{sign}.2f}%"
    if value.get("ci_low") is not None:
        text += f" [{100 * value['ci_low']:.2f}, {100 * value['ci_high']:.2f}]"
    return text


def records_of(result: dict[str, Any]) -> dict[tuple[str, str, str], dict[str, Any]]:
    return {(r["scenario"], r["algo"], r["variant"]): r for r in result["records"]}


def mean_of(result: dict, scenario: str, algo: str, variant: str, metric: str) -> float:
    return records_of(result)[(scenario, algo, variant)][metric]["mean"]


def span(values: list[float], digits: int = 1) -> str:
    """``low to high`` in percent (one number when they agree at ``digits``)."""
    low, high = pct(min(values), digits), pct(max(values), digits)
    return f"{low}%" if low == high else f"{low} to {high}%"


def budgets_text(budgets: dict[str, int]) -> str:
    """``3M steps per run for every learner``, or each learner's."""
    if len(set(budgets.values())) == 1 and len(budgets) == len(ALGOS):
        return f"{next(iter(budgets.values())) / 1e6:g}M steps per run for every learner"
    return ", ".join(f"{LEARNER_NAMES[a]} {b / 1e6:g}M" for a, b in budgets.items())


def pair_name(scenario: str, algo: str) -> str:
    return f"{SCENARIO_NAMES[scenario]}, {LEARNER_NAMES[algo]}"


# ------------------------------------------------------------------------------ the tables
def pair_table(result: dict[str, Any], pairs: list[tuple[str, str]] = PAIRS,
               paper: bool = True) -> list[str]:
    """Per pair: danger and success of plain / pessimistic / CCR, with CCR's Welch marks
    and (``paper``) the paper's numbers."""
    by_key = records_of(result)
    theirs = " the paper's |" if paper else ""
    lines = [f"| pair | danger: plain / pessimistic / CCR |{theirs} success: plain / "
             f"pessimistic / CCR |{theirs}", "|---|---|---|" + ("---|---|" if paper else "")]
    for scenario, algo in pairs:
        cells = []
        for metric in ("danger_frequency", "success_rate"):
            records = [by_key[(scenario, algo, v)][metric] for v in VARIANTS]
            ours = " / ".join(pct(r["mean"]) for r in records)
            cells.append(ours + welch_symbols(records[-1].get("welch", {})))
            if paper:
                cells.append(" / ".join(pct(PAPER[metric][(scenario, algo, v)])
                                        for v in VARIANTS))
        lines.append(f"| {pair_name(scenario, algo)} | " + " | ".join(cells) + " |")
    return lines + [""]


def claim_rows(result: dict[str, Any]) -> dict[str, str]:
    """The scorecard's claims and headline figures, in words, for one budget."""
    claims, headlines = result["claims"], result["headlines"]
    plain, pess = claims["danger_lower_vs_plain"], claims["danger_lower_vs_pessimistic"]
    above = claims["hidden_obstacle_success_above_both"]
    ratio = result["obstacle_distance_ratio_maddpg"]
    rows = {
        "CCR's danger below plain's": f"{plain['cells']} of 9 pairs ({plain['significant']} "
        f"significantly, {plain['significant_holm']} after Holm)",
        "CCR's danger below pessimistic's": f"{pess['cells']} of 9 ({pess['significant']} "
        "significantly)",
        "hidden-obstacle success above both baselines": f"{above['learners']} of 3 learners "
        f"({above['significant']} significantly)",
    }
    names = {
        "danger_reduction_vs_plain": "danger reduction, CCR vs plain",
        "danger_reduction_vs_pessimistic": "danger reduction, CCR vs pessimistic",
        "success_change_vs_pessimistic": "success change, CCR vs pessimistic",
        "success_change_vs_plain_turbulence": "success change, CCR vs plain, turbulence",
        "training_danger_share_maddpg_hidden_obstacle":
            "dangerous training steps, MADDPG+CCR / MADDPG, obstacle",
    }
    for key, name in names.items():
        rows[name] = interval(headlines[key])
    rows["followers' distance to the obstacle's centre, MADDPG+CCR / MADDPG"] = (
        f"{ratio['low']:.2f}x to {ratio['high']:.2f}x")
    return rows


PAPER_CLAIMS = {
    "CCR's danger below plain's": "8 of 9",
    "CCR's danger below pessimistic's": "9 of 9",
    "hidden-obstacle success above both baselines": "3 of 3",
    **{name: f"{100 * PAPER_HEADLINES[key]:.2f}%" for key, name in (
        ("danger_reduction_vs_plain", "danger reduction, CCR vs plain"),
        ("danger_reduction_vs_pessimistic", "danger reduction, CCR vs pessimistic"),
        ("success_change_vs_pessimistic", "success change, CCR vs pessimistic"),
        ("success_change_vs_plain_turbulence", "success change, CCR vs plain, turbulence"),
        ("training_danger_share_maddpg_hidden_obstacle",
         "dangerous training steps, MADDPG+CCR / MADDPG, obstacle"))},
    "followers' distance to the obstacle's centre, MADDPG+CCR / MADDPG": "1.2x to 4.7x",
}


def scorecard(tables: dict[str, dict[str, Any]]) -> list[str]:
    """The claims at every budget beside the paper's."""
    rows = {label: claim_rows(result) for label, result in tables.items()}
    lines = ["| claim | " + " | ".join(f"ours at {label}" for label in rows) + " | the paper |",
             "|---|" + "---|" * (len(rows) + 1)]
    for claim, paper in PAPER_CLAIMS.items():
        lines.append(f"| {claim} | " + " | ".join(r[claim] for r in rows.values())
                     + f" | {paper} |")
    return lines + [""]


def rliable_text(result: dict[str, Any], pairs: int = len(PAIRS)) -> str:
    agg = result["aggregates"]
    iqm = {m: {v: agg[m]["iqm"][v] for v in VARIANTS}
           for m in ("danger_frequency", "success_rate")}
    better = agg["danger_frequency"]["probability_of_improvement"]
    more = agg["success_rate"]["probability_of_improvement"]

    def probability(value: dict[str, float]) -> str:
        return f"{value['probability']:.2f} [{value['ci_low']:.2f}, {value['ci_high']:.2f}]"

    return (f"rliable over the {pairs} pairs (interquartile mean over seeds x pairs, stratified "
            "bootstrap): danger " + ", ".join(
                f"{interval(iqm['danger_frequency'][v], 'iqm')} {v}" for v in VARIANTS)
            + "; success " + ", ".join(f"{pct(iqm['success_rate'][v]['iqm'], 2)}% {v}"
                                       for v in VARIANTS)
            + f". The probability that a CCR run is safer than a plain run of the same pair "
            f"{probability(better['plain'])}, than a pessimistic run "
            f"{probability(better['pessimistic'])}; more successful "
            f"{probability(more['plain'])} and {probability(more['pessimistic'])}.")


def tables_section(folder: str, label: str, result: dict[str, Any]) -> list[str]:
    settings = result["settings"]
    seeds = settings["seeds"]
    return [
        f"## The paper's tables at {label} steps", "",
        f"All 9 scenario x learner pairs, {len(seeds)} seeds each (seeds {seeds[0]}-"
        f"{seeds[-1]}) of plain, pessimistic (penalty {settings['penalty']:g}) and CCR "
        f"(lambda {settings['lam']:g}), {budgets_text(result['budgets'])}, made on "
        f"{', '.join(result['devices'])}: [`{folder}/tables.md`]({folder}/tables.md) (the "
        "intervals, the reference controllers, the plateau checks, the figures; each cell's "
        "command, commit and device in its file under `cells/`). The final evaluation, "
        "mean over seeds in %; after CCR's numbers `↓*`/`↑*` mark CCR significantly "
        "below / above plain, `↓†`/`↑†` below / above pessimistic (Welch, p < 0.05, each "
        "test alone); the paper's numbers beside ours:", "",
        *pair_table(result),
        rliable_text(result), "",
    ]


# ------------------------------------------------------------------------------ the searches
# The name of each variant's searched value.
SEARCHED = {"ccr": "lambda", "pessimistic": "penalty", "lagrangian": "cost limit"}


def search_rows(search: dict[str, Any]) -> dict[float, tuple[float, float]]:
    """Each searched value's danger and success, averaged over the pairs and seeds."""
    return {row["value"]: (row["danger_frequency"]["mean"], row["success_rate"]["mean"])
            for row in search["aggregate"]}


def searches_section(searches: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    lines = [
        "## The searches", "",
        "CCR's lambda, the pessimistic penalty and the Lagrangian's cost limit (at its "
        "amendment's 2M steps), searched alike on the selection seeds "
        "100-102 over the 9 pairs by the protocol's rule (the lowest mean danger among the "
        "values whose mean success is at most 5 points below value 0's; "
        "[`docs/protocol.md`](../../docs/protocol.md)). Danger / success in %, averaged over "
        "pairs and seeds; the chosen value in bold:", "",
    ]
    for label, by_variant in searches.items():
        for variant, search in by_variant.items():
            name = SEARCHED[variant]
            chosen = search["selection"]["value"]
            rows = search_rows(search)
            cells = [(f"**{value:g}**" if value == chosen else f"{value:g}")
                     + f": {pct(d)} / {pct(s)}" for value, (d, s) in rows.items()]
            lines.append(f"* {label}, {name}: " + "; ".join(cells) + ".")
    return lines + [""]


# ------------------------------------------------------------------------------ the rest
def plain_section(tables: dict[str, dict[str, Any]]) -> list[str]:
    """The plain learners beside the paper's."""
    labels = list(tables)
    lines = [
        "## The plain learners against the paper's", "",
        "Plain danger / success in % on the tables' seeds; the paper's plain learners beside:",
        "",
        "| pair | " + " | ".join(f"ours at {label}" for label in labels) + " | the paper's |",
        "|---|" + "---|" * (len(labels) + 1),
    ]
    for scenario, algo in PAIRS:
        ours = [f"{pct(mean_of(r, scenario, algo, 'plain', 'danger_frequency'))} / "
                f"{pct(mean_of(r, scenario, algo, 'plain', 'success_rate'))}"
                for r in tables.values()]
        paper = " / ".join(pct(PAPER[m][(scenario, algo, "plain")])
                           for m in ("danger_frequency", "success_rate"))
        lines.append(f"| {pair_name(scenario, algo)} | " + " | ".join(ours) + f" | {paper} |")
    lines += ["", "Whether each plain learner's return had levelled off (the protocol's "
              "plateau test on its last 20% of evaluations):", ""]
    for label, result in tables.items():
        failed = [pair_name(r["scenario"], r["algo"]) for r in result["records"]
                  if r["variant"] == "plain" and r["return_plateau"].get("plateaued") is False]
        lines.append(f"* at {label}: {9 - len(failed)} of 9 pass"
                     + (f"; not levelled off: {'; '.join(failed)}." if failed else "."))
    return lines + [""]


def budgets_section(budgets: dict[str, dict[str, Any]]) -> list[str]:
    lines = ["## The budgets", "",
             "`experiments/budgets.py` trains the plain learners alone and proposes, per "
             "scenario and learner, the first budget from which the evaluated return has "
             "levelled off ([`docs/protocol.md`](../../docs/protocol.md)):", ""]
    for folder, (what, result) in budgets.items():
        cells = [pair_name(c["scenario"], c["algo"]) + (
                     f" {c['proposed_budget'] / 1e6:g}M" if c["proposed_budget"] is not None
                     else " none of the candidates")
                 + ("" if c["plateaued_at_budget"] else " (not levelled off at the budget)")
                 for c in result["cells"]]
        lines.append(f"* [`{folder}/`]({folder}/budgets.md), on {what}, candidates up to "
                     f"{budgets_text(result['budgets'])}: " + "; ".join(cells) + "."
                     + "".join(f" {line}" for line in on_policy_lines(result) if line)
                 + regime_budget_text(result))
    return lines + [""]


def regime_budget_text(result: dict[str, Any]) -> str:
    """The budget a budgets run in a study regime sets for it (the largest proposed budget
    of the study's pairs, ``docs/protocol.md``), or nothing for today's regime."""
    regime = result["settings"].get("regime", "today")
    if regime == "today":
        return ""
    chosen = "; ".join(f"{LEARNER_NAMES[algo]} **{steps:,}** steps"
                       for algo, steps in result["budgets"].items())
    return (f" The {regime} regime's budget (the largest proposed budget of the study's "
            f"pairs): {chosen}.")


def regimes_section(result: dict[str, Any]) -> list[str]:
    regimes = result["grid"]["regimes"]
    informative = sum(bool(r["informative"]) for r in regimes)
    return [
        "## The information regimes", "",
        "Where a teammate's trouble carries information: regimes set by the hazard's "
        "placement and the team's formation ([`docs/environment.md`](../../docs/environment.md), "
        "\"Regimes\"), measured by hand-written controllers before any learner trained there "
        f"([`regimes/regimes.md`](regimes/regimes.md)): {informative} of {len(regimes)} "
        "regimes are informative (the perfectly informed `team_informed` controller at most "
        "half as often in danger as `self_reactive`, at equal success). The regime chosen "
        "per scenario:", "",
        *chosen_regime_lines(regimes),
        "", f"Made by `{result['command']}` on {result['device']}.", "",
    ]


def summary_section(tables: dict[str, dict[str, Any]],
                    searches: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    lines = ["## Summary", ""]
    if tables and all(r["claims"]["danger_lower_vs_plain"]["significant_holm"] == 0
                      and r["claims"]["danger_lower_vs_pessimistic"]["cells"] == 0
                      for r in tables.values()):
        lines += ["**CCR's effect on danger does not reproduce here** with the paper's "
                  "learners at any budget: in no pair is CCR's danger significantly below "
                  "plain's after Holm's correction over the 9, and in none is it below the "
                  "tuned pessimistic baseline's.", ""]
    for label, result in tables.items():
        claims = result["claims"]
        plain = claims["danger_lower_vs_plain"]
        by_key = records_of(result)
        gaps = [abs(by_key[(s, a, "ccr")]["danger_frequency"]["mean"]
                    - by_key[(s, a, "plain")]["danger_frequency"]["mean"]) for s, a in PAIRS]
        pess = [by_key[(s, a, "pessimistic")]["danger_frequency"]["mean"] for s, a in PAIRS]
        ccr = [by_key[(s, a, "ccr")]["danger_frequency"]["mean"] for s, a in PAIRS]
        better = result["aggregates"]["danger_frequency"]["probability_of_improvement"]
        lines.append(
            f"* **At {label} steps** (lambda {result['settings']['lam']:g}, penalty "
            f"{result['settings']['penalty']:g}, {len(result['settings']['seeds'])} seeds per "
            f"cell): CCR's danger is within {math.ceil(1000 * max(gaps)) / 10:.1f} points of "
            "plain's in every "
            f"pair, below it in {plain['cells']} of 9 ({plain['significant_holm']} after Holm; "
            "the paper: 8 of 9); the paper's average danger reduction of "
            f"{100 * PAPER_HEADLINES['danger_reduction_vs_plain']:.2f}% comes out "
            f"{interval(result['headlines']['danger_reduction_vs_plain'])}; the probability "
            f"that a CCR run is safer than a plain one is {better['plain']['probability']:.2f}. "
            f"The tuned pessimistic baseline is in danger {span(pess)} of the time against "
            f"CCR's {span(ccr)}.")
    for label, by_variant in searches.items():
        parts = []
        for variant, search in by_variant.items():
            rows = search_rows(search)
            chosen = search["selection"]["value"]
            name = SEARCHED[variant]
            parts.append(f"{name} {chosen:g} ({pct(rows[chosen][0])}% danger at "
                         f"{pct(rows[chosen][1])}% success)")
        base = search_rows(next(iter(by_variant.values())))[0.0]
        alone = len(parts) == 1
        lines.append(f"* **The {'search' if alone else 'searches'} at {label}** chose "
                     + " and ".join(parts) + f", against {pct(base[0])}% at {pct(base[1])}% "
                     + ("unconstrained." if alone else "without either."))
    return lines + [""]


def explanations(tables: dict[str, dict[str, Any]]) -> list[str]:
    """The measured sizes behind the explanations below: how much of plain's danger the
    penalty removes per scenario, and CCR's change of success in turbulence."""
    lines = []
    for label, result in tables.items():
        by_key = records_of(result)
        removed = []
        for scenario in PAPER_SCENARIOS:
            shares = [1 - by_key[(scenario, a, "pessimistic")]["danger_frequency"]["mean"]
                      / by_key[(scenario, a, "plain")]["danger_frequency"]["mean"]
                      for a in ALGOS]
            removed.append(f"{SCENARIO_NAMES[scenario]} {span(shares, 0)}")
        turbulence = result["headlines"]["success_change_vs_plain_turbulence"]
        lines.append(f"* At {label}, the penalty removes this share of plain's danger: "
                     f"{', '.join(removed)}; CCR changes plain's success in turbulence by "
                     f"{interval(turbulence, signed=True)} (the paper: "
                     f"{100 * PAPER_HEADLINES['success_change_vs_plain_turbulence']:.2f}%).")
    return lines


STATIC_EXPLANATIONS = [
    "* **CCR barely changes behaviour at the lambda the rule selects**: the searches show no "
    "lambda that lowers danger over the pairs without costing success (above). Measured on "
    "the control policies, the team meets each hazard nearly together, so a follower "
    "seldom has the few steps of warning the reflex needs "
    "([`docs/environment.md`](../../docs/environment.md), `experiments/ccr_signal.py`).",
    "* **The pessimistic baseline was tuned here**, by the same search and rule as lambda, "
    "and it penalises the danger predicate itself; the paper does not say how its penalty "
    "was chosen. Ours is not a straw man.",
    "* **The plain learners are much safer than the paper's on the obstacle and in the "
    "wind** (the table above): they learn a way round, which leaves little danger for "
    "either treatment to remove there, so the averages over pairs are carried by "
    "turbulence, and on the obstacle a small base makes one pair's relative change large. "
    "Why the paper's learners did not, we cannot tell: it gives neither its scenarios' "
    "sizes nor its budgets. The scenarios stay as calibrated on the reference controllers: "
    "changing them now would be informed by how CCR and the penalty did.",
    "* **Training danger**: CCR lowers the danger of training no more than that of the "
    "final policies (the scorecard's training share, against the paper's 28%).",
    "",
    "## Results of an earlier protocol, removed", "",
    "The results committed before the environment and metrics were rebuilt were made under "
    "a protocol that could not measure what the paper claims (success counted at any "
    "height beyond the hazard, so fleeing the task scored 100% success and 0% danger; "
    "learners far from converged; only lambda tuned). They stay in the history "
    "([`docs/environment.md`](../../docs/environment.md)).", "",
    "## Speed", "",
    "Throughput of the environment and the learners on CPU and GPU, against JaxMARL: "
    "[`docs/speed.md`](../../docs/speed.md); the logs with command, commit and device: "
    "[`cpu/`](cpu/README.md) (`make bench` and the learners' sanity run on the 2-core CPU), "
    "[`gpu/`](gpu/README.md).", "",
    "## The files", "",
    "| folder | what | written by |", "|---|---|---|",
    "| [`tables/`](tables/tables.md) | Tables I and II at 3M steps: `tables.md`, `tables.json`, "
    "`cells/`, figures | `python experiments/tables.py --out experiments/results/tables "
    "--force` |",
    "| [`tables_6m/`](tables_6m/tables.md) | the same at 6M steps | `python experiments/tables.py "
    "--steps 6000000 --searches experiments/results/search_6m --out "
    "experiments/results/tables_6m --force` |",
    "| [`search/`](search/README.md) | the lambda (`ccr/`) and penalty (`pessimistic/`) "
    "searches at 3M | `python experiments/search.py --variant ccr` (and `pessimistic`) |",
    "| [`search_6m/`](search_6m) | both searches at 6M | the same, `--steps 6000000` |",
    "| [`search_lagrangian/`](search_lagrangian/search.md) | the Lagrangian's cost limit at "
    "2M | `python experiments/search.py --variant lagrangian --out "
    "experiments/results/search_lagrangian --force` |",
    "| [`constrained/`](constrained) | the Lagrangian's tables at 2M (`cells/`) and the "
    "pessimistic cells of penalty 1 at 2M (`tables_at_budget/`) | `python "
    "experiments/constrained.py --out experiments/results/constrained --force` (and "
    "`experiments/tables.py --steps 2000000 --lam 3 --penalty 1 --variants pessimistic`) |",
    "| [`budgets/`](budgets/budgets.md) | the plain learners' budgets | "
    "`python experiments/budgets.py` |",
    "| [`longer_budget/`](longer_budget/budgets.md) | the longer-budget check on the tables' "
    "seeds | `python experiments/budgets.py --tables-seeds` |",
    "| [`calibration/`](calibration/calibration.md) | the scenarios' calibration on reference "
    "controllers | `python experiments/calibrate.py` |",
    "| [`ccr_signal/`](ccr_signal/go_to_goal/ccr_signal.md) | whether CCR's signal is about "
    "emergencies | `python experiments/ccr_signal.py` |",
    "| [`regimes/`](regimes/regimes.md) | the controllers over the regimes' grid | "
    "`python experiments/calibrate.py --regimes` |",
    "| [`cpu/`](cpu/README.md) | `make bench` and sanity logs, 2-core CPU | "
    "the commands they name |",
    "| [`gpu/`](gpu/README.md) | GPU logs | the commands they name |",
    "",
]


