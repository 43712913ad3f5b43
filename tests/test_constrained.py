"""The constrained baseline's tables on made-up cells (:mod:`experiments.constrained_analysis`
and :mod:`experiments.constrained_report`): every variant read at the budget from longer
runs' evaluations, the rule applied there to each search, the limit met per seed, the
danger during training, the hypotheses, the report and its figures; and the command's
refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from experiments import constrained, results_report
from experiments.constrained_analysis import (
    PAIRS,
    hypotheses,
    pair_rows,
    scorecard,
    search_at,
    selection_at,
    table_cell_at,
)
from experiments.constrained_report import report

STEPS = [0, 200, 400, 600]
SEEDS = (0, 1, 2)
BUDGET = 400
# Per variant, each seed's final danger and success at the budget (400); other points differ.
AT_BUDGET = {"plain": (0.30, 0.90), "pessimistic": (0.02, 0.80), "ccr": (0.28, 0.90),
             "lagrangian": (0.05, 0.85)}


def table_cell(scenario: str, algo: str, variant: str, seeds: tuple[int, ...] = SEEDS) -> dict:
    danger, success = AT_BUDGET[variant]
    spread = np.array([-0.01, 0.0, 0.01])[: len(seeds)]

    def curve(value: float) -> list[list[float]]:  # value at 400, 0.5 elsewhere
        return [[0.5, 0.5, value + d, 0.5] for d in spread]

    history = {"danger_frequency": curve(danger), "success_rate": curve(success),
               "return": curve(-10.0), "learning_danger_steps": curve(1000.0),
               "env_steps": [STEPS] * len(seeds)}
    if variant == "lagrangian":
        history.update(lagrange_multiplier=curve(2.0), lagrange_cost=curve(0.06))
    return {"scenario": scenario, "algo": algo, "variant": variant, "seeds": list(seeds),
            "history": history, "params": {"lam": [1.0] * len(seeds)} if variant == "ccr" else
            {"penalty": [3.0] * len(seeds)}, "training": {"learning_starts": 100, "num_robots": 5},
            "commit": "abc", "device": "cpu:cpu x1"}


def search_cell(scenario: str, algo: str, values: list[float], danger: dict[float, float],
                success: dict[float, float]) -> dict:
    """A search cell whose runs' evaluation at the budget are ``danger`` and ``success`` by
    value (0.5 at the other points)."""
    grid_values = [v for v in values for _ in SEEDS]
    return {"scenario": scenario, "algo": algo, "env_steps": STEPS, "grid_values": grid_values,
            "history": {m: [[0.5, 0.5, table[v], 0.5] for v in grid_values]
                        for m, table in (("danger_frequency", danger),
                                         ("success_rate", success),
                                         ("return", {v: -1.0 for v in values}))}}


def test_a_cell_is_read_at_the_budget_not_at_its_end():
    cell = table_cell("turbulence", "iddpg", "plain")
    values = table_cell_at(cell, BUDGET)
    assert values["danger_frequency"] == pytest.approx([0.29, 0.30, 0.31])
    with pytest.raises(ValueError, match="no evaluation at 300 steps"):
        table_cell_at(cell, 300)


def test_the_rule_is_applied_at_the_budget():
    """Value 3 has the lowest danger among the values within 5 points of value 0's success
    at the budget (value 10 is safer but loses 20 points); at the end (600) every value
    ties at 0.5, so reading the wrong point would choose the smallest value."""
    values = [0.0, 1.0, 3.0, 10.0]
    cells = {pair: search_cell(*pair, values, {0.0: 0.3, 1.0: 0.2, 3.0: 0.1, 10.0: 0.01},
                               {0.0: 0.9, 1.0: 0.9, 3.0: 0.87, 10.0: 0.7}) for pair in PAIRS}
    chosen = selection_at(cells, BUDGET)
    assert chosen["value"] == 3.0 and chosen["eligible"] == [True, True, False]
    assert search_at(cells[PAIRS[0]], BUDGET)[10.0]["danger_frequency"] == [0.01] * 3
    with pytest.raises(ValueError, match="lacks"):
        selection_at({pair: cells[pair] for pair in PAIRS[:8]}, BUDGET)


def test_each_lagrangian_seed_is_checked_against_the_limit():
    cells = {(s, a, v): table_cell(s, a, v) for s, a in PAIRS for v in AT_BUDGET}
    rows = pair_rows(cells, BUDGET, cost_limit=0.05)
    row = rows[PAIRS[0]]
    assert row["meets_limit"] == [True, True, False]  # 0.04, 0.05, 0.06
    # The training danger: 1000 dangerous robot-steps over (400 - 100) steps x 5 robots.
    assert row["variants"]["plain"]["training_danger"][1] == pytest.approx(1000 / 1500)
    # The last interval's training danger (what the multiplier regulates): the dangerous
    # robot-steps counted from 200 to 400 over 200 steps x 5 robots.
    assert row["variants"]["lagrangian"]["last_interval_danger"] == pytest.approx(
        [(1000 + d - 0.5) / 1000 for d in (-0.01, 0.0, 0.01)])
    assert row["meets_limit_in_training"] == [False, False, False]
    assert pair_rows(cells, BUDGET, cost_limit=0.9995)[PAIRS[0]]["meets_limit_in_training"] == [
        True, True, False]
    assert row["welch"]["plain"]["danger_frequency"]["difference"] == pytest.approx(-0.25)
    assert row["welch"]["plain"]["danger_frequency"]["significant"]
    found = hypotheses(rows, cost_limit=0.05)
    assert len(found["pairs_plain_above_limit"]) == 9 and found["h_l1_holds"]
    assert found["versus_pessimistic"]["danger_frequency"]["significantly_higher"] == 9
    assert not hypotheses(rows, cost_limit=0.01)["h_l1_holds"]  # 0.05 [0.025, 0.075] > 0.01


def test_the_scorecard_counts_directions_significance_and_holm():
    """Danger against plain: 3 pairs much lower (p 0.001, which survive Holm over 9: the
    first threshold is 0.05 / 9), 2 lower with p 0.03 (significant alone, not after Holm),
    1 higher with p 0.01, 3 lower without significance. Success counts the other way: a
    positive difference is better."""
    tests = ([(-0.1, 0.001)] * 3 + [(-0.05, 0.03)] * 2 + [(0.05, 0.01)]
             + [(-0.01, 0.4)] * 3)
    rows = {}
    for pair, (difference, p) in zip(PAIRS, tests, strict=True):
        test = {"difference": difference, "p": p, "significant": p < 0.05}
        rows[pair] = {"welch": {base: {m: test for m in ("danger_frequency", "success_rate",
                                                           "training_danger")}
                                for base in ("plain", "pessimistic", "ccr")}}
    found = scorecard(rows)
    danger = found["plain"]["danger_frequency"]
    assert danger["better"] == {"cells": 8, "significant": 5, "significant_holm": 3}
    assert danger["worse"] == {"cells": 1, "significant": 1, "significant_holm": 0}
    assert danger["of"] == 9
    success = found["ccr"]["success_rate"]  # "CCR better than the Lagrangian" is "worse"
    assert success["better"] == {"cells": 1, "significant": 1, "significant_holm": 0}
    assert success["worse"] == {"cells": 8, "significant": 5, "significant_holm": 3}


def write_cells(folder: Path, cells: dict[str, dict]) -> None:
    (folder / "cells").mkdir(parents=True)
    for name, cell in cells.items():
        (folder / "cells" / f"{name}.json").write_text(json.dumps(cell))


def test_the_report_says_what_the_cells_hold(tmp_path):
    tables, searches, own = tmp_path / "tables", tmp_path / "searches", tmp_path / "own"
    write_cells(tables, {f"{s}-{a}-{v}": table_cell(s, a, v) for s, a in PAIRS
                         for v in ("plain", "pessimistic", "ccr")})
    values = [0.0, 0.01, 0.05]
    write_cells(own, {f"{s}-{a}": search_cell(s, a, values, {0.0: 0.3, 0.01: 0.01, 0.05: 0.05},
                                               {0.0: 0.9, 0.01: 0.5, 0.05: 0.88})
                      for s, a in PAIRS})
    lagrangian = {(s, a): table_cell(s, a, "lagrangian") for s, a in PAIRS}
    settings = constrained.Settings(cost_limit=0.05, seeds=SEEDS, steps=BUDGET, eval_every=200)
    out = tmp_path / "out"
    out.mkdir()
    result, text, figures = report(lagrangian, settings, tables, searches, own,
                                   {"cost_limit": "given"}, out, [], resamples=20)
    assert result["selections_at_budget"]["lagrangian"]["value"] == 0.05
    assert "lacks" in result["selections_at_budget"]["ccr"]["missing"]
    assert "cost limit **0.05**" in text and "2 of 3" in text
    assert "what the multiplier regulates): 0 of 3" in text
    assert result["tables_values"]["pessimistic"] == {"penalty": [3.0]}
    assert [f.name for f in figures] == [f"multiplier_{s}.png" for s in
                                         ("hidden_obstacle", "strong_wind", "turbulence")]
    assert all(f.stat().st_size > 0 for f in figures)
    wrong = tmp_path / "wrong"
    write_cells(wrong, {f"{s}-{a}-{v}": {**table_cell(s, a, v), "seeds": [7, 8, 9]}
                        for s, a in PAIRS for v in ("plain", "pessimistic", "ccr")})
    with pytest.raises(ValueError, match="not \\[0, 1, 2\\]"):
        report(lagrangian, settings, wrong, searches, own, {}, out, [], resamples=20)


def test_the_command_needs_a_finished_search_or_a_limit(tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        constrained.main(["--out", str(tmp_path / "out"), "--lagrangian-search",
                          str(tmp_path / "none")])
    err = capsys.readouterr().err
    assert stopped.value.code == 2 and len(err.strip().splitlines()) == 1
    assert "no Lagrangian search result" in err and "--cost-limit" in err
    with pytest.raises(SystemExit) as stopped:
        constrained.main(["--out", str(tmp_path / "out"), "--cost-limit", "2"])
    assert stopped.value.code == 2 and "--cost-limit" in capsys.readouterr().err


@pytest.mark.slow  # nine quick programs compiled and trained
def test_the_command_trains_the_nine_cells_and_writes_the_tables(tmp_path, capsys):
    """The quick mode end to end: the nine Lagrangian cells (2 seeds, 400 steps), then the
    report against made-up baselines evaluated at 400 steps; a second invocation trains
    nothing and writes the same tables."""
    tables = tmp_path / "tables"
    write_cells(tables, {f"{s}-{a}-{v}": table_cell(s, a, v, seeds=(0, 1)) for s, a in PAIRS
                         for v in ("plain", "pessimistic", "ccr")})
    out = tmp_path / "out"
    argv = ["--quick", "--cost-limit", "0.05", "--out", str(out), "--tables", str(tables),
            "--searches", str(tmp_path / "none"), "--lagrangian-search", str(tmp_path / "no")]
    assert constrained.main(argv) == 0
    text = (out / "constrained.md").read_text()
    assert "Quick mode" in text and "cost limit **0.05**" in text
    cell = json.loads((out / "cells" / "turbulence-maac-lagrangian.json").read_text())
    assert cell["training"]["transform"]["warmup_episodes"] == 2
    assert len(cell["history"]["lagrange_multiplier"]) == 2
    assert sorted(p.name for p in out.glob("multiplier_*.png")) == [
        f"multiplier_{s}.png" for s in ("hidden_obstacle", "strong_wind", "turbulence")]
    capsys.readouterr()
    assert constrained.main(argv) == 0
    assert "9 of 9 programs already done" in capsys.readouterr().err
    assert (out / "constrained.md").read_text() == text


def test_the_results_report_says_what_the_constrained_tables_show(tmp_path):
    """A ``constrained/constrained.json`` in the results folder gives the report its section
    (IQMs, the choices at the budget, seeds meeting the limit); without it there is none."""
    tables, own = tmp_path / "tables", tmp_path / "own"
    write_cells(tables, {f"{s}-{a}-{v}": table_cell(s, a, v) for s, a in PAIRS
                         for v in ("plain", "pessimistic", "ccr")})
    write_cells(own, {f"{s}-{a}": search_cell(s, a, [0.0, 0.05], {0.0: 0.3, 0.05: 0.05},
                                               {0.0: 0.9, 0.05: 0.88}) for s, a in PAIRS})
    lagrangian = {(s, a): table_cell(s, a, "lagrangian") for s, a in PAIRS}
    settings = constrained.Settings(cost_limit=0.05, seeds=SEEDS, steps=BUDGET, eval_every=200)
    results = tmp_path / "results"
    (results / "constrained").mkdir(parents=True)
    assert "constrained baseline" not in results_report.report(results)
    result, _, _ = report(lagrangian, settings, tables, tmp_path / "none", own,
                          {"cost_limit": "given on the command line"},
                          results / "constrained", [], resamples=20)
    (results / "constrained" / "constrained.json").write_text(json.dumps(result))
    text = results_report.report(results)
    assert "## The constrained baseline (Lagrangian) at 400 steps" in text
    assert "cost_limit 0.05" in text and "hidden_obstacle-iddpg 2/3" in text
    assert "| danger | 30.0% | 2.0% | 28.0% | 5.0% |" in text


def test_the_rules_other_choices_at_the_budget_are_reported_beside(tmp_path):
    """Where the rule at the budget picks another penalty and lambda than the tables' (3
    and 1 here), the report names the command that trains their cells at the budget, then
    reads each variant's from the first folder holding all of them (the tables at the
    budget, else longer tables read at the budget) and tests the Lagrangian against them."""
    tables, searches, own = tmp_path / "tables", tmp_path / "searches", tmp_path / "own"
    write_cells(tables, {f"{s}-{a}-{v}": table_cell(s, a, v) for s, a in PAIRS
                         for v in ("plain", "pessimistic", "ccr")})
    write_cells(searches / "pessimistic", {
        f"{s}-{a}": search_cell(s, a, [0.0, 1.0, 3.0], {0.0: 0.3, 1.0: 0.05, 3.0: 0.01},
                                {0.0: 0.9, 1.0: 0.88, 3.0: 0.5}) for s, a in PAIRS})
    write_cells(searches / "ccr", {
        f"{s}-{a}": search_cell(s, a, [0.0, 1.0, 3.0], {0.0: 0.3, 1.0: 0.3, 3.0: 0.2},
                                {0.0: 0.9, 1.0: 0.9, 3.0: 0.9}) for s, a in PAIRS})
    write_cells(own, {f"{s}-{a}": search_cell(s, a, [0.0, 0.05], {0.0: 0.3, 0.05: 0.05},
                                               {0.0: 0.9, 0.05: 0.88}) for s, a in PAIRS})
    lagrangian = {(s, a): table_cell(s, a, "lagrangian") for s, a in PAIRS}
    settings = constrained.Settings(cost_limit=0.05, seeds=SEEDS, steps=BUDGET, eval_every=200)
    out, beside, longer = tmp_path / "out", tmp_path / "beside", tmp_path / "longer"
    out.mkdir()

    def reported(*folders: Path) -> tuple[dict, str]:
        result, text, _ = report(lagrangian, settings, tables, searches, own, {}, out, [],
                                 resamples=20, at_budget=folders)
        return result, text

    result, text = reported(beside, longer)
    assert result["at_rule_values"]["values"] == {"pessimistic": 1.0, "ccr": 3.0}
    assert (f"Not yet: the pessimistic and CCR cells of the rule's values are in none of "
            f"{beside}, {longer} (`python experiments/tables.py --steps 400 --penalty 1 --lam 3 "
            f"--variants pessimistic ccr --out {beside} --force`)") in text
    # Longer tables of lambda 3 on the same seeds, evaluated at the budget: CCR's are read.
    write_cells(longer, {f"{s}-{a}-ccr": {**table_cell(s, a, "ccr"), "params": {"lam": [3.0] * 3}}
                         for s, a in PAIRS})
    # Pessimistic cells at the tables' penalty: not these.
    write_cells(beside, {f"{s}-{a}-pessimistic": table_cell(s, a, "pessimistic")
                         for s, a in PAIRS})
    result, text = reported(beside, longer)
    assert "Not yet: the pessimistic cells of the rule's values are in none of" in text
    assert "--variants pessimistic --out" in text
    assert result["at_rule_values"]["sources"] == {"ccr": str(longer)}
    for s, a in PAIRS[:-1]:  # one pair short of the 9: not read from there
        (beside / "cells" / f"{s}-{a}-pessimistic.json").write_text(json.dumps(
            {**table_cell(s, a, "pessimistic"), "params": {"penalty": [1.0] * 3}}))
    assert "Not yet: the pessimistic cells" in reported(beside, longer)[1]
    s, a = PAIRS[-1]
    (beside / "cells" / f"{s}-{a}-pessimistic.json").write_text(json.dumps(
        {**table_cell(s, a, "pessimistic"), "params": {"penalty": [1.0] * 3}}))
    result, text = reported(beside, longer)
    assert result["at_rule_values"]["sources"] == {"pessimistic": str(beside),
                                                   "ccr": str(longer)}
    assert f"Read from: pessimistic's cells, `{beside}`; CCR's cells, `{longer}`" in text
    row = result["at_rule_values"]["pairs"]["hidden_obstacle-iddpg"]
    assert row["welch"]["pessimistic"]["danger_frequency"]["difference"] == pytest.approx(0.03)
    assert "| hidden obstacle, IDDPG | pessimistic (penalty 1) | 2.00%" in text
