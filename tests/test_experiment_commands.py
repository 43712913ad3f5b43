"""The experiments' commands refuse bad input with one line and status 2, before compiling:
unknown names, too few seeds, seeds that mix selection and reporting, budgets that end
before learning starts, and an ``--out`` that would overwrite committed results."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

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


def test_committed_results_need_force(search, tables, tmp_path, capsys, monkeypatch):
    import ledger

    results = tmp_path / "results"
    (results / "search" / "ccr").mkdir(parents=True)
    (results / "search" / "ccr" / "search.json").write_text("{}")
    monkeypatch.setattr(ledger, "RESULTS", results)
    refused(search, ["--variant", "ccr", "--out", str(results / "search" / "ccr")], capsys,
            "holds committed results", "--force")
    refused(tables, ["--lam", "30", "--penalty", "1", "--out", str(results / "search")],
            capsys, "--force")


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
