"""The experiments' commands refuse bad input with one line and status 2, before compiling:
unknown names, too few seeds, seeds that mix selection and reporting, budgets that end
before learning starts, and an ``--out`` that would overwrite committed results."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"{name}_commands", EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def search():
    return load("search")


@pytest.fixture(scope="module")
def tables():
    return load("tables")


@pytest.fixture(scope="module")
def budgets():
    return load("budgets")


@pytest.fixture(scope="module")
def merge():
    return load("merge")


def refused(module, argv, capsys, *fragments):
    with pytest.raises(SystemExit) as exit_:
        module.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line]
    assert len(lines) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.mark.parametrize("argv, fragments", [
    (["--variant", "both"], ("--variant",)),
    (["--variant", "ccr", "--scenarios", "lava"], ("--scenarios",)),
    (["--variant", "ccr", "--algos", "ppo"], ("--algos",)),
    (["--variant", "ccr", "--seeds", "1"], ("--seeds",)),
    (["--variant", "ccr", "--values", "0"], ("--values",)),
    (["--variant", "ccr", "--seed-offset", "5"], ("overlaps the tables' seeds",)),
    (["--variant", "ccr", "--steps", "20000"], ("(--steps) 20,000 ends before learning",)),
])
def test_search_refuses_bad_input(search, argv, fragments, tmp_path, capsys):
    out = tmp_path / "never"
    refused(search, [*argv, "--out", str(out)], capsys, *fragments)
    assert not out.exists()


@pytest.mark.parametrize("argv, fragments", [
    (["--algos", "ppo"], ("--algos",)),
    (["--scenarios", "lava"], ("--scenarios",)),
    (["--seeds", "1"], ("--seeds",)),
    (["--seed-offset", "0"], ("--seed-offset 0", "tables' seeds 0-9")),
    (["--seed-offset", "99"], ("selection seeds 100-102",)),
    (["--steps", "20000"], ("(--steps) 20,000 ends before learning",)),
    (["--candidate-every", "0"], ("--candidate-every",)),
])
def test_budgets_refuse_bad_input(budgets, argv, fragments, tmp_path, capsys):
    out = tmp_path / "never"
    refused(budgets, [*argv, "--out", str(out)], capsys, *fragments)
    assert not out.exists()


def test_the_proposed_budget_is_where_the_return_stays_level(budgets):
    """Made-up curves evaluated every 100 steps: rising until 1,000, then flat; a rise after
    a flat stretch moves the proposal past it; a curve rising to the end has none."""
    steps = np.arange(0, 2001, 100)
    noise = np.array([[0.0], [0.1], [-0.1]])
    rising_then_flat = np.minimum(steps, 1000) / 100 + noise
    candidates = list(range(500, 2001, 500))
    checks, proposed = budgets.check_budgets(steps, rising_then_flat, candidates)
    assert [c["budget"] for c in checks] == candidates
    assert [c["plateaued"] for c in checks] == [False, False, True, True]
    assert proposed == 1500
    relapse = rising_then_flat + np.where(steps > 1600, (steps - 1600) / 100, 0.0)
    assert budgets.check_budgets(steps, relapse, candidates)[1] is None
    assert budgets.check_budgets(steps, steps / 100 + noise, candidates)[1] is None


def test_committed_results_need_force(search, tables, budgets, tmp_path, capsys, monkeypatch):
    import ledger

    results = tmp_path / "results"
    (results / "search" / "ccr").mkdir(parents=True)
    (results / "search" / "ccr" / "search.json").write_text("{}")
    monkeypatch.setattr(ledger, "RESULTS", results)
    refused(search, ["--variant", "ccr", "--out", str(results / "search" / "ccr")], capsys,
            "holds committed results", "--force")
    refused(tables, ["--lam", "30", "--penalty", "1", "--out", str(results / "search")],
            capsys, "--force")
    refused(budgets, ["--out", str(results / "search")], capsys, "--force")


def test_tables_refuse_bad_input(tables, tmp_path, capsys, monkeypatch):
    out = str(tmp_path / "never")
    refused(tables, ["--quick"], capsys, "--quick needs --out")
    refused(tables, ["--quick", "--seeds", "1", "--out", out], capsys, "--seeds")
    refused(tables, ["--lam", "30", "--penalty", "1", "--seed-offset", "95", "--out", out],
            capsys, "selection seeds")
    refused(tables, ["--lam", "30", "--penalty", "1", "--steps", "1000", "--out", out],
            capsys, "ends before learning starts")
    monkeypatch.setattr(tables, "SEARCHES", tmp_path / "no-searches")
    refused(tables, ["--penalty", "1", "--out", out], capsys, "no ccr search result", "--lam")


def results_folder(path: Path, settings: dict, records: list[dict], cells: dict[str, str]) -> Path:
    (path / "cells").mkdir(parents=True)
    (path / "invocations.json").write_text(json.dumps({"settings": settings,
                                                       "invocations": records}))
    for name, text in cells.items():
        (path / "cells" / name).write_text(text)
    return path


def test_merge_gathers_cells_and_records_of_folders_made_apart(merge, tmp_path, capsys):
    settings = {"seeds": [200, 201], "steps": None, "scenarios": ["turbulence"], "algos": ["iddpg"]}
    wider = {**settings, "scenarios": ["turbulence", "strong_wind"]}
    into = results_folder(tmp_path / "into", settings, [{"command": "a"}],
                          {"turbulence-iddpg.json": "A"})
    one = results_folder(tmp_path / "one", wider, [{"command": "b"}],
                         {"turbulence-iddpg.json": "A", "strong_wind-iddpg.json": "B"})
    two = results_folder(tmp_path / "two", settings, [{"command": "a"}, {"command": "c"}],
                         {"nominal-iddpg.json": "C"})
    assert merge.main([str(one), str(two), "--into", str(into)]) == 0
    assert sorted(p.name for p in (into / "cells").iterdir()) == [
        "nominal-iddpg.json", "strong_wind-iddpg.json", "turbulence-iddpg.json"]
    ledger = json.loads((into / "invocations.json").read_text())
    assert [r["command"] for r in ledger["invocations"]] == ["a", "b", "c"]
    assert ledger["settings"] == settings
    assert "2 cell(s) copied" in capsys.readouterr().out
    assert merge.main([str(one), "--into", str(into)]) == 0  # again: nothing new
    assert "0 cell(s) copied" in capsys.readouterr().out


def test_merge_refuses_what_does_not_fit_and_writes_nothing(merge, tmp_path, capsys,
                                                             monkeypatch):
    import ledger

    settings = {"seeds": [200, 201], "steps": None}
    into = results_folder(tmp_path / "into", settings, [], {"turbulence-iddpg.json": "A"})
    before = (into / "invocations.json").read_text()
    other = results_folder(tmp_path / "other", {**settings, "steps": 5}, [], {"x.json": "X"})
    refused(merge, [str(other), "--into", str(into)], capsys, "other settings")
    clash = results_folder(tmp_path / "clash", settings, [{"command": "b"}],
                           {"turbulence-iddpg.json": "B", "y.json": "Y"})
    refused(merge, [str(clash), "--into", str(into)], capsys, "turbulence-iddpg.json differs")
    (tmp_path / "empty").mkdir()
    refused(merge, [str(tmp_path / "empty"), "--into", str(into)], capsys, "no invocations.json")
    refused(merge, [str(into), "--into", str(into)], capsys, "--into must not be")
    assert sorted(p.name for p in (into / "cells").iterdir()) == ["turbulence-iddpg.json"]
    assert (into / "invocations.json").read_text() == before
    monkeypatch.setattr(ledger, "RESULTS", tmp_path)
    refused(merge, [str(clash), "--into", str(into)], capsys, "--into", "--force")
