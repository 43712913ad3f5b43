"""``tables.md``: the tables in the paper's layout, written from what ``tables.json``
holds (:func:`experiments.tables_statistics.summary`)."""

from __future__ import annotations

import numpy as np

from ccrjax.run.stats import format_mean_ci
from ccrjax.run.sweep_grid import nonfinite_text
from ccrjax.training import ALGOS
from experiments import protocol
from experiments.ledger import (
    duration,
    invocation_line,
)
from experiments.paper import PAPER_SCENARIOS
from experiments.tables_grid import (
    CONTROLLERS,
    LEARNER_NAMES,
    SCENARIO_NAMES,
    VARIANT_SUFFIX,
    VARIANTS,
    grid_jobs,
)
from experiments.tables_statistics import HEADLINES


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.2f}%"


def welch_symbols(marks: dict) -> str:
    """``↓*`` / ``↑*``: CCR significantly below / above plain; ``↓†`` / ``↑†``: below /
    above pessimistic (Welch, p < 0.05); nothing where the difference is not significant."""
    text = ""
    for base, symbol in (("plain", "*"), ("pessimistic", "†")):
        mark = marks.get(base, {})
        if mark.get("significant"):
            text += (" ↓" if mark["difference"] < 0 else " ↑") + symbol
    return text


def _cell_text(record_metric: dict, percent: bool, digits: int = 2) -> str:
    scale, unit = (100.0, "%") if percent else (1.0, "")
    text = (format_mean_ci(record_metric, percent, digits) if np.isfinite(record_metric["mean"])
            else "none")
    if "seeds_measured" in record_metric:
        text += f" (n={record_metric['seeds_measured']})"
    text += welch_symbols(record_metric.get("welch", {}))
    if "paper" in record_metric:
        text += f" ({record_metric['paper'] * scale:.2f}{unit})"
    return text


def family_of(result: dict) -> tuple[str, ...]:
    """The learners a ``tables.json`` holds (the paper's three where it does not say)."""
    return tuple(result.get("algos", ALGOS))


def table(result: dict, metric: str, title: str, percent: bool, digits: int = 2) -> list[str]:
    by_key = {(r["scenario"], r["algo"], r["variant"]): r for r in result["records"]}
    controllers = {(c["scenario"], c["controller"]): c for c in result["controllers"]}
    header = "| | " + " | ".join(SCENARIO_NAMES[s] for s in PAPER_SCENARIOS) + " |"
    lines = [f"### {title}", "", header, "|---|" + "---|" * len(PAPER_SCENARIOS)]
    for name, label in CONTROLLERS.items():
        if metric not in controllers[(PAPER_SCENARIOS[0], name)]:
            continue  # a training count: the controllers do not train
        scale, unit = (100.0, "%") if percent else (1.0, "")
        lines.append(f"| {label} | " + " | ".join(
            f"{controllers[(s, name)][metric] * scale:.2f}{unit}" for s in PAPER_SCENARIOS) + " |")
    for algo in family_of(result):
        for variant in VARIANTS:
            name = LEARNER_NAMES[algo] + VARIANT_SUFFIX[variant]
            cells = [_cell_text(by_key[(s, algo, variant)][metric], percent, digits)
                     for s in PAPER_SCENARIOS]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines + [""]


def _interval(value: dict, key: str = "mean") -> str:
    text = _pct(value.get(key))
    if value.get("ci_low") is not None:
        text += f" [{_pct(value['ci_low'])}, {_pct(value['ci_high'])}]"
    return text


def tables_markdown(result: dict) -> str:
    settings = result["settings"]
    h = result["headlines"]
    p = result["paper_headlines"]
    seeds = settings["seeds"]
    algos = family_of(result)
    paper_family = algos == ALGOS
    pairs = len(PAPER_SCENARIOS) * len(algos)
    programs = len(grid_jobs(algos))
    names_text = ", ".join(LEARNER_NAMES[a] for a in algos)
    lines = [
        ("# The paper's Tables I and II, re-run with ccrjax" if paper_family else
         f"# Tables I and II for the on-policy learners ({names_text})"),
        "",
        *([protocol.quick_note(), ""] if settings.get("quick") else []),
        f"Made on {', '.join(result['devices'])} at commit(s) "
        f"{', '.join(f'`{c}`' for c in result['commits'])}; the {programs} programs' compile "
        f"and training time add up to {duration(result['programs_seconds'])}. Invocations:",
        "",
        *(invocation_line(run, programs) for run in result["invocations"]),
        "",
        f"{len(seeds)} seeds per cell (seeds {seeds[0]} to {seeds[-1]}); environment steps per "
        f"run {result['budgets']}; CCR at lambda {settings['lam']:g} "
        f"({result['sources']['lam']}), pessimistic penalty {settings['penalty']:g} "
        f"({result['sources']['penalty']}). Each cell: the final evaluation "
        f"({settings['eval_episodes']} fresh episodes per seed, deterministic policies), the "
        "mean and its 95% confidence interval over seeds (Student t, clipped to the metric's "
        "range); after a CCR cell, `↓*` / `↑*`: CCR significantly below / above plain, `↓†` / "
        f"`↑†`: below / above pessimistic (Welch, p < 0.05, each test alone: {4 * pairs} of "
        "them; a "
        "seed's three variants share their evaluation episodes, and plain and pessimistic "
        "their initial parameters (CCR's networks also read the shared scores), a pairing "
        "these unpaired tests ignore: conservative where the variants' results "
        "correlate); "
        + ("in parentheses the paper's number (IDDPG is the paper's DDPG: one DDPG per "
           "robot)" if paper_family else "no paper's number: the paper trains no on-policy "
           "learner") + ". Reference rows: hand-written "
        f"controllers over {settings['controller_episodes']} episodes (no learning).",
        "",
    ]
    lines += table(result, "danger_frequency", "Table I: dangerous-behaviour frequency", True)
    lines += table(result, "success_rate", "Table II: success rate", True)
    lines += table(result, "target_distance", "Final distance to the target", False)
    lines += table(result, "hazard_distance", "Average distance to the hazard centre", False)
    lines += table(result, "return", "Return (environment reward per robot and episode)", False)
    lines += table(result, "learning_danger_steps", "Dangerous robot-steps during training, "
                   "from the start of learning to the end (the paper's cumulative training "
                   "danger)", False, digits=0)
    by_key = {(r["scenario"], r["algo"], r["variant"]): r for r in result["records"]}
    lines += [
        "### Behaviour on the hidden obstacle",
        "",
        "The followers' closest approach to the obstacle's surface: every robot but the first "
        "to arrive, counting only robots that end in the target area (keeping away by giving "
        "up does not count); mean over the seeds that had such a follower (n: those seeds of "
        "all), 95% CI. The paper: with CCR the followers steer away before touching.",
        "",
        "| | " + " | ".join(VARIANTS) + " |",
        "|---|" + "---|" * len(VARIANTS),
    ]
    for algo in algos:
        lines.append(f"| {LEARNER_NAMES[algo]} | " + " | ".join(
            _cell_text(by_key[("hidden_obstacle", algo, v)]["followers_closest_successful"],
                       False) for v in VARIANTS) + " |")
    lines.append("")
    plain_records = [r for r in result["records"] if r["variant"] == "plain"]
    not_levelled = [r for r in plain_records if r["return_plateau"].get("plateaued") is False]
    undetermined = [r for r in plain_records if r["return_plateau"].get("plateaued") is None]
    lines += [
        "### Did the plain learners converge?",
        "",
        "The plain learner's evaluated return has plateaued if the mean of its last 20% of "
        "evaluations lies within the 95% interval of the 20% before (passing means the test "
        "found no rise: a slow rise smaller than that interval passes). "
        + _convergence_text(not_levelled, undetermined),
        "",
        *plateau_table(plain_records),
        "### Did training stay finite?",
        "",
        nonfinite_text(result["nonfinite"], f"the {result['runs']} runs"),
        "",
        f"### Aggregates over the {pairs} scenario x learner pairs (rliable)",
        "",
        "Interquartile mean over seeds x pairs with 95% stratified-bootstrap intervals, and "
        "the probability that a CCR run improves on a baseline run of the same pair (lower "
        "danger, higher success; 0.5 = no difference).",
        "",
        "| | IQM danger | IQM success | P(CCR safer) | P(CCR more successful) |",
        "|---|---|---|---|---|",
    ]
    agg = result["aggregates"]
    for variant in VARIANTS:
        danger = agg["danger_frequency"]["iqm"][variant]
        success = agg["success_rate"]["iqm"][variant]
        if variant == "ccr":
            improve = ("", "")
        else:
            improve = tuple(
                _probability(agg[m]["probability_of_improvement"][variant])
                for m in ("danger_frequency", "success_rate"))
        lines.append(f"| {variant} | {_interval(danger, 'iqm')} | {_interval(success, 'iqm')} | "
                     f"{improve[0]} | {improve[1]} |")
    lines += [
        "",
        "### The paper's headline figures, recomputed",
        "",
        f"Averages over the scenario x learner pairs (all {pairs}, or turbulence's "
        f"{len(algos)}) of the "
        "relative change of the mean, as the paper computes them (its numbers follow from "
        "its tables this way); 95% bootstrap intervals over seeds, leaving out the "
        "resamples in which a pair's base mean is 0 (counted where there are any). Each "
        "pair's own change is listed below: a base near 0 makes one pair's change large "
        "enough to carry the average. The training share counts dangerous robot-steps from "
        "the start of learning.",
        "",
        "| figure | ours | paper" + ("" if paper_family else " (its off-policy learners)")
        + " |",
        "|---|---|---|",
    ]
    names = {
        "danger_reduction_vs_plain": "danger reduction, CCR vs plain",
        "danger_reduction_vs_pessimistic": "danger reduction, CCR vs pessimistic",
        "success_change_vs_pessimistic": "success change, CCR vs pessimistic",
        "success_change_vs_plain_turbulence": "success change, CCR vs plain (turbulence)",
        "training_danger_share_maddpg_hidden_obstacle":
            "training dangerous steps since learning started, MADDPG+CCR / MADDPG "
            "(hidden obstacle)",
    }
    for key, label in names.items():
        value = h[key]
        if value is None:  # a MADDPG figure, and MADDPG is not in this family
            continue
        ours = _interval(value)
        notes = []
        if value.get("left_out"):
            notes.append(f"{value['left_out']} pair(s) with a zero base left out")
        if value.get("resamples_dropped"):
            notes.append(f"{value['resamples_dropped']} resamples with a zero base left out")
        if notes:
            ours += f" ({'; '.join(notes)})"
        lines.append(f"| {label} | {ours} | {_pct(p[key])} |")
    ratio = result["obstacle_distance_ratio_maddpg"]
    if ratio is not None:
        lines.append(
            "| average distance to the obstacle's centre, MADDPG+CCR / MADDPG, robot by robot "
            f"in arrival order (hidden obstacle) | {ratio['low']:.2f}x to {ratio['high']:.2f}x "
            f"({', '.join(f'{r:.2f}' for r in ratio['by_rank'])}) | {ratio['paper'][0]:g}x to "
            f"{ratio['paper'][1]:g}x |")
    lines += [
        "",
        "Each pair's relative change:",
        "",
        "| pair | " + " | ".join(names[key] for key in HEADLINES) + " |",
        "|---|" + "---|" * len(HEADLINES),
    ]
    by_pair: dict[str, dict[str, float | None]] = {}
    for key in HEADLINES:
        for name, change in zip(h[key]["pair_names"], h[key]["per_pair"], strict=True):
            by_pair.setdefault(name, {})[key] = change
    for name, changes in by_pair.items():
        lines.append(f"| {name} | " + " | ".join(
            (_pct(changes[key]) if changes[key] is not None else "zero base")
            if key in changes else "" for key in HEADLINES) + " |")
    c = result["claims"]
    lines += [
        "",
        "### Scorecard: do the paper's claims hold here?",
        "",
        f"* CCR's danger below plain's in {c['danger_lower_vs_plain']['cells']} of {pairs} "
        f"cells ({c['danger_lower_vs_plain']['significant']} significantly, "
        f"{c['danger_lower_vs_plain']['significant_holm']} after Holm's correction over the "
        f"{pairs}); the paper: 8 of 9.",
        f"* below pessimistic's in {c['danger_lower_vs_pessimistic']['cells']} of {pairs} "
        f"({c['danger_lower_vs_pessimistic']['significant']} significantly, "
        f"{c['danger_lower_vs_pessimistic']['significant_holm']} after Holm); the paper: 9 "
        "of 9.",
        f"* hidden-obstacle success above both baselines for "
        f"{c['hidden_obstacle_success_above_both']['learners']} of {len(algos)} learners "
        f"({c['hidden_obstacle_success_above_both']['significant']} significantly); the "
        "paper: 3 of 3.",
        "",
    ]
    return "\n".join(lines)


def plateau_table(plain_records: list[dict]) -> list[str]:
    """The plain learners' plateau checks with their sizes: the mean return of the last
    20% of evaluations, that of the 20% before with its 95% interval, and the change, so
    a reader sees whether a curve that failed the test rose by a hair or was still
    learning."""
    lines = ["| plain learner | return, last 20% | return, 20% before [95% CI] | change | "
             "levelled off |", "|---|---|---|---|---|"]
    for r in plain_records:
        check = r["return_plateau"]
        name = f"{SCENARIO_NAMES[r['scenario']]}, {LEARNER_NAMES[r['algo']]}"
        if "last" not in check:
            lines.append(f"| {name} | | | | undetermined: {check.get('why', '')} |")
            continue
        change = check["last"] - check["previous"]
        relative = (f" ({100 * change / abs(check['previous']):+.1f}%)"
                    if check["previous"] != 0 else "")
        verdict = {True: "yes", False: "**no**", None: "undetermined"}[check["plateaued"]]
        lines.append(
            f"| {name} | {check['last']:.2f} | {check['previous']:.2f} "
            f"[{check['ci_low']:.2f}, {check['ci_high']:.2f}] | {change:+.2f}{relative} "
            f"| {verdict} |")
    return lines + [""]


def _convergence_text(not_levelled: list[dict], undetermined: list[dict]) -> str:
    def names(records: list[dict]) -> str:
        return ", ".join(f"{r['scenario']} {LEARNER_NAMES[r['algo']]}" for r in records)

    if not not_levelled and not undetermined:
        return "It did in every cell."
    text = f"It did **not** in: {names(not_levelled)}." if not_levelled else ""
    if undetermined:
        text += (" " if text else "") + ("Undetermined (too few evaluations or seeds, or a "
                                         f"NaN return) in: {names(undetermined)}.")
    return text


def _probability(value: dict) -> str:
    return (f"{value['probability']:.2f} [{value['ci_low']:.2f}, {value['ci_high']:.2f}]")

