"""The results report (``experiments/results/README.md``) is generated from the committed
result files: the committed one is what they give, the same files give the same text, and
a changed number in a result file changes the report."""

from __future__ import annotations

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
    for pattern in ("tables*/tables.json", "search*/*/search.json", "*budget*/budgets.json",
                    "regimes/regimes.json"):
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
