"""The results report (``experiments/results/README.md``) is generated from the committed
result files: the committed one is what they give, the same files give the same text, and
a changed number in a result file changes the report."""

from __future__ import annotations

import functools
import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "experiments" / "results"


@pytest.fixture(scope="module")
def report():
    return importlib.import_module("experiments.results_report")


def test_the_committed_report_is_what_the_result_files_give(report):
    assert (RESULTS / "README.md").read_text() == report.report(RESULTS)


def test_the_same_files_give_the_same_report(report):
    assert report.report(RESULTS) == report.report(RESULTS)


def copy_results(tmp_path: Path) -> Path:
    """The result files the report reads (not the cells or figures)."""
    out = tmp_path / "results"
    for pattern in ("tables*/tables.json", "search*/*/search.json", "search*/search.json",
                    "constrained/constrained.json", "*budget*/budgets.json",
                    "study/budgets*/budgets.json", "regimes/regimes.json"):
        for path in RESULTS.glob(pattern):
            target = out / path.relative_to(RESULTS)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(path, target)
    return out


def test_a_changed_result_changes_the_report(report, tmp_path):
    out = copy_results(tmp_path)
    assert report.report(out) == report.report(RESULTS)
    path = out / "tables" / "tables.json"
    result = json.loads(path.read_text())
    result["claims"]["danger_lower_vs_pessimistic"]["cells"] = 4
    for record in result["records"]:
        if (record["scenario"], record["algo"], record["variant"]) == (
                "turbulence", "maddpg", "ccr"):
            record["danger_frequency"]["mean"] = 0.123
    path.write_text(json.dumps(result))
    text = report.report(out)
    assert "| turbulence, MADDPG | 39.8 / 2.0 / 12.3" in text
    assert "| CCR's danger below pessimistic's | 4 of 9" in text
    assert "does not reproduce here" not in text  # the verdict follows the numbers


def test_the_lagrangian_search_is_reported_with_its_choice(report, tmp_path):
    out = copy_results(tmp_path)
    path = out / "search_lagrangian" / "search.json"
    result = json.loads(path.read_text())
    result["selection"]["value"] = 0.05
    for row in result["aggregate"]:
        if row["value"] == 0.05:
            row["danger_frequency"]["mean"] = 0.0123
    path.write_text(json.dumps(result))
    text = report.report(out)
    assert "**The search at 2M** chose cost limit 0.05 (1.2% danger at" in text
    assert "2M, cost limit: 0: " in text and "; **0.05**: 1.2 / " in text
    path.unlink()
    assert "2M, cost limit:" not in report.report(out)


def test_the_constrained_tables_reach_the_summary(report, tmp_path):
    out = copy_results(tmp_path)
    path = out / "constrained" / "constrained.json"
    result = json.loads(path.read_text())
    result["aggregates"]["danger_frequency"]["iqm"]["lagrangian"]["iqm"] = 0.0456
    result["hypotheses"]["limit_met_within_spread"] = 1
    result["hypotheses"]["versus_pessimistic"]["danger_frequency"]["significantly_higher"] = 2
    path.write_text(json.dumps(result))
    text = report.report(out)
    summary = text.split("## The claims")[0]
    assert "* **The Lagrangian at 2M steps** (cost limit 0.3, 10 seeds per cell" in summary
    assert "danger 4.6% against plain's" in summary
    assert "the Lagrangian meets it within its seeds' spread in 1;" in summary
    assert "significantly less dangerous than the Lagrangian in 2 of 9 pairs, CCR in 0." in summary
    path.unlink()
    assert "The Lagrangian at 2M steps" not in report.report(out)


def test_a_study_regimes_budget_is_reported(report, tmp_path):
    out = copy_results(tmp_path)
    path = out / "study" / "budgets_column" / "budgets.json"
    result = json.loads(path.read_text())
    result["budgets"] = {"maddpg": 2_400_000}
    path.write_text(json.dumps(result))
    assert ("The column regime's budget (the largest proposed budget of the study's pairs): "
            "MADDPG **2,400,000** steps.") in report.report(out)


def test_missing_folders_are_left_out(report, tmp_path):
    out = copy_results(tmp_path)
    shutil.rmtree(out / "tables_6m")
    shutil.rmtree(out / "regimes")
    text = report.report(out)
    assert "## The paper's tables at 6M steps" not in text
    assert "## The information regimes" not in text
    assert "## The paper's tables at 3M steps" in text


@pytest.mark.slow  # three processes that start JAX
def test_the_command_checks_and_refuses_in_one_line(tmp_path):
    out = copy_results(tmp_path)
    command = [sys.executable, "-m", "experiments.results_report", "--results", str(out)]
    check = subprocess.run([*command, "--check"], capture_output=True, text=True, cwd=ROOT)
    assert check.returncode == 1 and "is not the report" in check.stderr
    assert subprocess.run(command, capture_output=True, cwd=ROOT).returncode == 0
    assert subprocess.run([*command, "--check"], capture_output=True, cwd=ROOT).returncode == 0
    bad = subprocess.run([*command[:-1], str(tmp_path / "none")], capture_output=True,
                         text=True, cwd=ROOT)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--results" in bad.stderr


def made_up_on_policy_tables(danger, success, monkeypatch) -> dict:
    """``tables.json`` of the on-policy family from made-up cells (5 seeds each):
    ``danger(scenario, algo, variant)`` and ``success(...)`` give a cell's mean (the
    bootstraps at 100 resamples, enough for made-up numbers)."""
    statistics = importlib.import_module("experiments.tables_statistics")
    for name in ("aggregates", "headline"):
        monkeypatch.setattr(statistics, name,
                            functools.partial(getattr(statistics, name), resamples=100))
    grid = importlib.import_module("experiments.tables_grid")
    offsets = [-0.02, -0.01, 0.0, 0.01, 0.02]
    cells = {}
    for scenario, algo in importlib.import_module("experiments.results_on_policy").PAIRS:
        for variant in grid.VARIANTS:
            final = {m: [0.5] * 5 for m in grid.METRICS}
            final["return"] = [-10.0] * 5
            final["danger_frequency"] = [danger(scenario, algo, variant) + o for o in offsets]
            final["success_rate"] = [success(scenario, algo, variant) + o for o in offsets]
            cells[(scenario, algo, variant)] = {
                "scenario": scenario, "algo": algo, "variant": variant,
                "final": final, "seeds": [0, 1, 2, 3, 4], "return_plateau": None,
                "train_seconds_of_program": 1.0, "compile_seconds_of_program": 1.0,
                "device": "cpu:cpu x1", "commit": "abc"}
    settings = grid.Settings(lam=3.0, penalty=10.0, algos=("ippo", "mappo"),
                             seeds=(0, 1, 2, 3, 4))
    return statistics.summary(cells, settings, [], {}, {})


def test_the_on_policy_section_counts_the_amendments_hypotheses_per_pair(monkeypatch):
    """H-P1 holds where CCR's danger is significantly below plain's at success within 5
    points; H-P2 where it is not significantly below the penalty's; the section says what
    is not made yet."""
    section = importlib.import_module("experiments.results_on_policy")

    def danger(scenario, algo, variant):
        if variant == "ccr":
            return {"hidden_obstacle": 0.10, "turbulence": 0.10}.get(scenario, 0.30)
        return {"plain": 0.30, "pessimistic": 0.20}[variant]

    def success(scenario, algo, variant):  # in turbulence CCR costs MAPPO 10 points
        return 0.80 if (scenario, algo, variant) == ("turbulence", "mappo", "ccr") else 0.90

    tables = made_up_on_policy_tables(danger, success, monkeypatch)
    found = section.hypotheses(tables)
    assert found["H-P1"] == 3  # the obstacle's two and turbulence's IPPO
    assert found["H-P2"] == 2  # the wind's two: CCR below the penalty elsewhere
    assert [p["H-P1"] for p in found["pairs"]] == [True, True, True, False, False, False]
    text = "\n".join(section.on_policy_section({}, tables))
    assert "holds in 3 of 6 pairs (hidden obstacle, IPPO; hidden obstacle, MAPPO; " \
           "turbulence, IPPO)" in text
    assert "| turbulence, MAPPO | 30.0 / 20.0 / 10.0 ↓* ↓† | 90.0 / 90.0 / 80.0 ↓* ↓† |" in text
    assert "lambda: not made yet (`python experiments/search.py --variant ccr" in text
    assert "not made yet (`python experiments/tables.py" not in text
    summary = "\n".join(section.summary_lines(tables))
    assert "H-P1 (lower danger at most 5 points of success below plain's) holds in 3 of 6 " \
           "(hidden obstacle, IPPO; hidden obstacle, MAPPO; turbulence, IPPO); H-P2 (no " \
           "lower than the tuned penalty's) in 2 of 6: the penalty is in danger 20.0% of " \
           "the time against CCR's 10.0 to 30.0%." in summary
    assert "CCR's danger is below plain's in 4 of 6 pairs (4 significantly" in summary
    assert section.summary_lines(None) == []
    empty = "\n".join(section.on_policy_section({}, None))
    assert "Their tables are not made yet (`python experiments/tables.py --algos ippo " \
           "mappo" in empty
