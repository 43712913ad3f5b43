"""What a budgets run (:mod:`experiments.budgets`) concludes from its cells, and what it
writes: the plateau check at each candidate budget and the proposed budget per cell
(:func:`check_budgets`), the protocol's rules over cells (one budget for all, the
on-policy family's, a regime's), ``budgets.md`` and the curves figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ccrjax.run.stats import format_mean_ci, plateau
from ccrjax.run.sweep_grid import nonfinite_runs, nonfinite_text, summarise
from ccrjax.training import ALGOS
from ccrjax.viz.plots import Curves, draw_curves
from experiments import protocol
from experiments.ledger import duration, invocation_line
from experiments.paper import PAPER_SCENARIOS

FINAL_METRICS = ("return", "success_rate", "danger_frequency")


def check_budgets(steps: np.ndarray, returns: np.ndarray, candidates: list[int]
                  ) -> tuple[list[dict[str, Any]], int | None]:
    """The plateau check of the curves ``returns`` ``[seeds, points]`` (evaluated at
    ``steps`` ``[points]``) cut at each candidate budget, and the proposed budget: the
    smallest candidate from which on every checked candidate plateaus (``None`` if the
    last one does not). Candidates with too few evaluations to check are left out."""
    checks = []
    for budget in candidates:
        points = int(np.searchsorted(steps, budget, side="right"))
        try:
            result = plateau(returns[:, :points])
        except ValueError:
            continue
        checks.append({"budget": int(budget), **result})
    proposed = None
    for index in range(len(checks)):
        if all(c["plateaued"] for c in checks[index:]):
            proposed = checks[index]["budget"]
            break
    return checks, proposed


def one_budget_for_all(cells: list[dict[str, Any]]) -> dict[str, Any]:
    """The longer-budget check's rule (docs/protocol.md, amendment of 2026-11-26) over the
    checked ``cells``: the smallest candidate budget at which every cell's plateau check
    passes (``budget``), or, if none does, the largest candidate, flagged (``passed``
    false); ``failing`` names, per candidate, the cells whose check fails there or could not
    be made."""
    candidates = sorted({check["budget"] for cell in cells for check in cell["checks"]})
    failing = {}
    for budget in candidates:
        failing[budget] = [
            f"{cell['scenario']}-{cell['algo']}" for cell in cells
            if not any(c["budget"] == budget and c["plateaued"] for c in cell["checks"])]
    passing = [budget for budget in candidates if not failing[budget]]
    if passing:
        return {"budget": passing[0], "passed": True, "failing": failing}
    return {"budget": candidates[-1] if candidates else None, "passed": False,
            "failing": failing}


def largest_proposed_budget(cells: list[dict[str, Any]], cap: int) -> dict[str, Any]:
    """The largest of the checked ``cells``' proposed budgets (each the smallest candidate
    from which on every candidate's check passes), so that by it every cell's plain learner
    has levelled off on the budget seeds: the on-policy learners' budget (docs/protocol.md,
    amendment of 2026-12-02) and a regime's (addition of 2026-12-03). If a cell proposes
    none (its return still moving at the end), ``cap`` (the budgets run's length), flagged
    (``passed`` false); ``moving`` names such cells."""
    moving = [f"{cell['scenario']}-{cell['algo']}" for cell in cells
              if cell["proposed_budget"] is None]
    if moving or not cells:
        return {"budget": cap, "passed": False, "moving": moving}
    return {"budget": max(cell["proposed_budget"] for cell in cells), "passed": True,
            "moving": []}


def on_policy_lines(result: dict[str, Any]) -> list[str]:
    """The on-policy learners' budget by :func:`largest_proposed_budget` once the six cells of the
    budget seeds (the paper's scenarios x IPPO and MAPPO) exist."""
    cells = {(cell["scenario"], cell["algo"]): cell for cell in result["cells"]
             if cell["algo"] in protocol.ON_POLICY_ALGOS and cell["scenario"] in PAPER_SCENARIOS}
    if not cells or tuple(result["settings"]["seeds"]) != protocol.BUDGET_SEEDS:
        return []
    wanted = len(PAPER_SCENARIOS) * len(protocol.ON_POLICY_ALGOS)
    if len(cells) < wanted:
        return ["", f"The on-policy learners' budget (the largest proposed budget of their "
                f"{wanted} cells): not yet, {len(cells)} of them are made."]
    rule = largest_proposed_budget(list(cells.values()),
                            max(cell["budget"] for cell in cells.values()))
    if rule["passed"]:
        return ["", f"The on-policy learners' budget (the largest proposed budget of their "
                f"{wanted} cells): **{rule['budget']:,}** steps."]
    return ["", f"The on-policy learners' budget: **{rule['budget']:,}** steps (the budgets "
            f"run's length), flagged: the return was still moving at the end for "
            f"{', '.join(rule['moving'])}."]


def final_stats(cell: dict[str, Any], metric: str) -> dict[str, Any]:
    """Mean and 95% interval (within the metric's range) over seeds of ``metric`` at the
    last evaluation."""
    return summarise(np.array([curve[-1] for curve in cell["curves"][metric]]), metric)


def seeds_text(seeds: list[int]) -> str:
    """Which seeds a summary's cells were trained on, by purpose."""
    if tuple(seeds) == protocol.TABLE_SEEDS:
        return (f"The tables' seeds {seeds} (the longer-budget check of docs/protocol.md, "
                "amendment of 2026-11-26: the plain learners alone)")
    return f"Budget seeds {seeds}"


def candidates_text(settings: dict[str, Any]) -> str:
    named = settings.get("candidate_budgets") or ()
    if named:
        return "candidate budgets " + ", ".join(f"{c:,}" for c in sorted(named))
    return f"candidate budgets every {settings['candidate_every']:,} steps"


def rule_lines(result: dict[str, Any]) -> list[str]:
    """Where the candidates are named (the longer-budget check): the check at each
    candidate per cell, and the budget for all by :func:`one_budget_for_all` once every
    scenario and learner of the paper has its cell."""
    cells = result["cells"]
    candidates = sorted({check["budget"] for cell in cells for check in cell["checks"]})
    if not candidates or not result["settings"].get("candidate_budgets"):
        return []
    lines = ["", "Plateau check at each candidate budget (the last 20% of evaluations up to "
             "it against the 95% interval of the 20% before; the change is the last "
             "window's mean return minus the one before):", "",
             "| learner | scenario | " + " | ".join(f"{c:,}" for c in candidates) + " |",
             "|---|---|" + "---|" * len(candidates)]
    for cell in cells:
        by_budget = {check["budget"]: check for check in cell["checks"]}
        shown = []
        for budget in candidates:
            check = by_budget.get(budget)
            shown.append("not checked" if check is None else
                         f"{protocol.PLATEAU_WORDS[check['plateaued']]} "
                         f"({check['last'] - check['previous']:+.2f})")
        lines.append(f"| {cell['algo']} | {cell['scenario']} | " + " | ".join(shown) + " |")
    made = {(cell["scenario"], cell["algo"]) for cell in cells}
    regime = result["settings"].get("regime", protocol.DEFAULT_REGIME)
    if regime == protocol.DEFAULT_REGIME:
        wanted = {(s, a) for s in PAPER_SCENARIOS for a in ALGOS}
        name = "One budget for all"
        how = "the smallest candidate at which every plain learner's check passes"
    else:  # the study's budget in its regime (amendment of 2026-12-01, addition 2026-12-03)
        wanted = {(s, a) for s in protocol.STUDY_SCENARIOS for a in protocol.STUDY_ALGOS}
        name = f"The `{regime}` regime's budget"
        how = ("the largest of the study pairs' proposed budgets, each the smallest candidate "
               "from which on every check passes")
    lines.append("")
    if not wanted <= made:
        lines.append(f"{name} ({how}): not yet, {len(wanted & made)} of the "
                     f"{len(wanted)} scenario x learner cells are made.")
        return lines
    if regime != protocol.DEFAULT_REGIME:
        rule = largest_proposed_budget(
            [cell for cell in cells if (cell["scenario"], cell["algo"]) in wanted],
            max(candidates))
        lines.append(f"{name} ({how}): **{rule['budget']:,}** steps" + (
            "." if rule["passed"] else f", flagged: the return was still moving at the end "
            f"for {', '.join(rule['moving'])}."))
        return lines
    rule = one_budget_for_all([cell for cell in cells if (cell["scenario"], cell["algo"])
                               in wanted])
    if rule["passed"]:
        lines.append(f"{name} ({how}): **{rule['budget']:,}** steps.")
    else:
        failing = rule["failing"][rule["budget"]]
        lines.append(f"{name}: no candidate passes for every plain learner, so "
                     f"**{rule['budget']:,}** steps, flagged: at it the check fails for "
                     f"{', '.join(failing)}.")
    return lines


def budgets_markdown(result: dict[str, Any]) -> str:
    settings = result["settings"]
    lines = [
        "# Budgets of the plain learners",
        "",
        *([protocol.quick_note(variants=False, regime=settings.get(
            "regime", protocol.DEFAULT_REGIME)), ""] if settings.get("quick") else []),
        f"{seeds_text(settings['seeds'])}{protocol.regime_text(settings)}; "
        "environment steps per seed: "
        + ", ".join(f"{steps:,} ({algo})" for algo, steps in result["budgets"].items()) + "; "
        f"evaluation every {settings['eval_every']:,} steps, {settings['eval_episodes']} "
        f"episodes per seed; {candidates_text(settings)}. "
        "Plateaued: the mean over seeds of the last 20% of evaluations lies within the 95% "
        "Student-t interval of the 20% before. Proposed: the smallest candidate from which "
        "on every candidate plateaus (none: still moving at the end). Final values: mean "
        "and 95% interval over seeds at the last evaluation. Made by:",
        "",
        *(invocation_line(run) for run in result["invocations"]),
        "",
        "| learner | scenario | plateaued at the end | proposed budget | return | success | "
        "danger | program |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for cell in result["cells"]:
        proposed = cell["proposed_budget"]
        lines.append(
            f"| {cell['algo']} | {cell['scenario']} | "
            f"{protocol.PLATEAU_WORDS[cell['plateaued_at_budget']]} | "
            f"{'none' if proposed is None else f'{proposed:,}'} | "
            f"{format_mean_ci(final_stats(cell, 'return'), False, digits=1)} | "
            f"{format_mean_ci(final_stats(cell, 'success_rate'), True, digits=1)} | "
            f"{format_mean_ci(final_stats(cell, 'danger_frequency'), True, digits=1)} | "
            f"{duration(cell['train_s'] + cell['compile_s'])} on {cell['device']} at "
            f"`{cell['commit']}` |")
    skipped = [line for cell in result["cells"]
               for line in nonfinite_runs(cell, f"{cell['scenario']}, {cell['algo']}")]
    runs = sum(len(cell["seeds"]) for cell in result["cells"])
    lines += [*rule_lines(result), *on_policy_lines(result), "",
              nonfinite_text(skipped, f"the {runs} runs") if runs else "No cell is made yet."]
    return "\n".join(lines) + "\n"


def draw_budget_curves(cells: dict[tuple[str, str], dict], out: Path, quick: bool = False,
                       seeds: str = "budget seeds") -> list[Path]:
    """``curves_<algo>.png``: return, success and danger along training per scenario
    (``quick``: the titles say the quick mode; ``seeds``: which seeds they show)."""
    paths = []
    for algo in dict.fromkeys(a for _, a in cells):
        curves = Curves()
        for (scenario, cell_algo), cell in cells.items():
            if cell_algo == algo:
                curves.add(scenario, cell["env_steps"],
                           {m: np.asarray(cell["curves"][m]) for m in FINAL_METRICS})
        path = out / f"curves_{algo}.png"
        draw_curves(curves, path, metrics=FINAL_METRICS,
                    title=f"{protocol.QUICK_FIGURE if quick else ''}plain {algo}, {seeds}: "
                    "is the return still moving?")
        paths.append(path)
    return paths
