"""The experiments' commands refuse bad input with one line and status 2, before compiling:
unknown names, too few seeds, seeds that mix selection and reporting, budgets that end
before learning starts, and an ``--out`` that would overwrite committed results."""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ccrjax.agents.ddpg import DDPGConfig

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"


def load(name: str):
    return importlib.import_module(f"experiments.{name}")


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
def budgets_report():
    return load("budgets_report")


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
    (["--variant", "ccr", "--seed-offset", "200"], ("overlaps the budgets' seeds",)),
    (["--variant", "ccr", "--quick", "--seed-offset", "8"], ("overlaps the tables' seeds",)),
    (["--variant", "ccr", "--steps", "20000"], ("(--steps) 20,000 ends before learning",)),
    (["--variant", "ccr", "--steps", "130000"], ("--steps 130,000 runs as 200,000",)),
    (["--variant", "ccr", "--algos", "maddpg", "ippo"],
     ("mixes the off-policy learners", "name one family's learners")),
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
    (["--steps", "250001"], ("--steps 250,001 runs as 300,000", "whole evaluation")),
    (["--candidate-every", "0"], ("--candidate-every",)),
    (["--candidate-every", "4000000"], ("above the budget 3,000,000 of iddpg",)),
    (["--seed-offset", "0"], ("is --tables-seeds",)),
    (["--tables-seeds", "--seeds", "4"], ("--tables-seeds fixes the seeds", "--seeds")),
    (["--tables-seeds", "--seed-offset", "0", "--candidate-every", "1000"],
     ("leave out --seed-offset and --candidate-every",)),
    (["--tables-seeds", "--quick"], ("--quick has seeds of its own",)),
    (["--tables-seeds", "--steps", "2000000"],
     ("candidates 3,000,000 is above the budget 2,000,000",)),
    (["--regime", "sideways"], ("--regime", "'today', 'column'")),
    (["--regime", "column", "--candidate-every", "120000"],
     ("--regime column checks its own candidate budgets", "--candidate-every")),
    (["--regime", "column", "--tables-seeds"], ("leave out --tables-seeds",)),
    (["--regime", "column", "--eval-every", "100000"],
     ("--eval-every 100,000 runs as 100,080", "whole iterations of 240")),
])
def test_budgets_refuse_bad_input(budgets, argv, fragments, tmp_path, capsys):
    out = tmp_path / "never"
    refused(budgets, [*argv, "--out", str(out)], capsys, *fragments)
    assert not out.exists()


def test_the_proposed_budget_is_where_the_return_stays_level(budgets_report):
    """Made-up curves evaluated every 100 steps: rising until 1,000, then flat; a rise after
    a flat stretch moves the proposal past it; a curve rising to the end has none."""
    steps = np.arange(0, 2001, 100)
    noise = np.array([[0.0], [0.1], [-0.1]])
    rising_then_flat = np.minimum(steps, 1000) / 100 + noise
    candidates = list(range(500, 2001, 500))
    checks, proposed = budgets_report.check_budgets(steps, rising_then_flat, candidates)
    assert [c["budget"] for c in checks] == candidates
    assert [c["plateaued"] for c in checks] == [False, False, True, True]
    assert proposed == 1500
    relapse = rising_then_flat + np.where(steps > 1600, (steps - 1600) / 100, 0.0)
    assert budgets_report.check_budgets(steps, relapse, candidates)[1] is None
    assert budgets_report.check_budgets(steps, steps / 100 + noise, candidates)[1] is None


def test_one_budget_for_all_is_the_smallest_candidate_every_learner_passes(budgets_report):
    """The longer-budget check's rule (docs/protocol.md, amendment of 2026-11-26) on made-up
    checks: the smallest candidate at which every cell passes, even where a cell passed at
    a smaller one; the largest, flagged with the cells that fail there, where none does."""
    def cell(name: str, passes: dict[int, bool | None]) -> dict:
        return {"scenario": name, "algo": "iddpg",
                "checks": [{"budget": b, "plateaued": p} for b, p in passes.items()]}

    cells = [cell("a", {3: True, 4: False, 6: True}), cell("b", {3: False, 4: True, 6: True}),
             cell("c", {3: True, 4: True, 6: True})]
    rule = budgets_report.one_budget_for_all(cells)
    assert (rule["budget"], rule["passed"]) == (6, True)
    assert rule["failing"] == {3: ["b-iddpg"], 4: ["a-iddpg"], 6: []}
    cells[0]["checks"][1]["plateaued"] = True
    assert budgets_report.one_budget_for_all(cells)["budget"] == 4
    cells[2]["checks"][2]["plateaued"] = None  # undetermined counts as not passing
    cells[1]["checks"][1]["plateaued"] = False
    rule = budgets_report.one_budget_for_all(cells)
    assert (rule["budget"], rule["passed"]) == (6, False)
    assert rule["failing"][6] == ["c-iddpg"]
    # The summary says it once every scenario and learner of the paper has its cell.
    nine = [{"scenario": s, "algo": a, "checks": [
        {"budget": b, "plateaued": b >= (4_500_000 if (s, a) == ("turbulence", "maac") else
                                         3_000_000), "last": 1.0, "previous": 0.5}
        for b in (3_000_000, 4_500_000, 6_000_000)]}
        for a in budgets_report.ALGOS for s in budgets_report.PAPER_SCENARIOS]
    named = {"candidate_budgets": [3_000_000, 4_500_000, 6_000_000]}
    assert budgets_report.rule_lines({"cells": nine, "settings": {"candidate_budgets": []}}) == []
    text = "\n".join(budgets_report.rule_lines({"cells": nine, "settings": named}))
    assert "| maac | turbulence | **no** (+0.50) | yes (+0.50) | yes (+0.50) |" in text
    assert "every plain learner's check passes): **4,500,000** steps." in text
    fewer = {"cells": nine[1:], "settings": named}
    assert "not yet, 8 of the 9" in "\n".join(budgets_report.rule_lines(fewer))
    for cell in nine:  # IDDPG fails everywhere: the largest candidate, flagged
        for check in cell["checks"]:
            check["plateaued"] = check["plateaued"] and cell["algo"] != "iddpg"
    assert ("no candidate passes for every plain learner, so **6,000,000** steps, flagged: at "
            "it the check fails for hidden_obstacle-iddpg, turbulence-iddpg, strong_wind-iddpg"
            ) in "\n".join(budgets_report.rule_lines({"cells": nine, "settings": named}))


def test_the_on_policy_budget_is_the_largest_proposed_by_their_six_cells(budgets_report):
    """The on-policy learners' rule (docs/protocol.md, amendment of 2026-12-02): the largest
    proposed budget of the six plain cells on the budget seeds; the budgets run's length,
    flagged with the cells still moving, where one proposes none; nothing before all six."""
    proposals = {("hidden_obstacle", "ippo"): 1_500_000, ("turbulence", "ippo"): 750_000,
                 ("strong_wind", "ippo"): 1_000_000, ("hidden_obstacle", "mappo"): 2_250_000,
                 ("turbulence", "mappo"): 500_000, ("strong_wind", "mappo"): 1_250_000}
    cells = [{"scenario": s, "algo": a, "budget": 4_000_000, "proposed_budget": p}
             for (s, a), p in proposals.items()]
    cells.append({"scenario": "hidden_obstacle", "algo": "maddpg", "budget": 3_000_000,
                  "proposed_budget": 3_000_000})  # not of the family: ignored
    result = {"cells": cells, "settings": {"seeds": [200, 201, 202]}}
    assert budgets_report.largest_proposed_budget(cells[:6], 4_000_000) == {
        "budget": 2_250_000, "passed": True, "moving": []}
    assert "their 6 cells): **2,250,000** steps." in "\n".join(
        budgets_report.on_policy_lines(result))
    assert "not yet, 5 of them" in "\n".join(budgets_report.on_policy_lines(
        {**result, "cells": cells[1:]}))
    cells[4]["proposed_budget"] = None
    text = "\n".join(budgets_report.on_policy_lines(result))
    assert ("**4,000,000** steps (the budgets run's length), flagged: the return was still "
            "moving at the end for turbulence-mappo.") in text
    assert budgets_report.on_policy_lines({**result, "settings": {"seeds": list(range(10))}}) == []


def test_the_tables_seeds_check_runs_the_protocols_longer_budget(budgets):
    """--tables-seeds: the tables' seeds, 6M steps, the candidates 3M, 4.5M and 6M, as the
    amendment of 2026-11-26 says."""
    args = budgets.build_parser().parse_args(["--tables-seeds"])
    settings = budgets.settings_from(args)
    assert settings.seeds == tuple(range(10))
    assert settings.budget("maac") == 6_000_000
    assert settings.candidates("iddpg") == [3_000_000, 4_500_000, 6_000_000]
    assert budgets.settings_from(budgets.build_parser().parse_args([])).seeds == (200, 201, 202)


def test_an_out_among_the_committed_results_is_named_unless_forced(tmp_path):
    """The guard itself (the commands below use it): a folder of committed results, or a
    new one among them, needs --force; a folder elsewhere does not."""
    from experiments import ledger

    results = tmp_path / "results"
    (results / "search" / "ccr").mkdir(parents=True)
    (results / "search" / "ccr" / "search.json").write_text("{}")
    assert "holds committed results" in ledger.committed_results_problem(
        results / "search" / "ccr", False, results)
    assert "inside the committed results" in ledger.committed_results_problem(
        results / "never_made", False, results)
    assert ledger.committed_results_problem(results / "search" / "ccr", True, results) is None
    assert ledger.committed_results_problem(tmp_path / "elsewhere", False, results) is None
    assert ledger.committed_results_problem(ledger.RESULTS / "x", False)  # the real ones


def test_committed_results_need_force(search, tables, budgets, tmp_path, capsys, monkeypatch):
    from experiments import ledger

    results = tmp_path / "results"
    (results / "search" / "ccr").mkdir(parents=True)
    (results / "search" / "ccr" / "search.json").write_text("{}")
    monkeypatch.setattr(ledger, "RESULTS", results)
    refused(search, ["--variant", "ccr", "--out", str(results / "search" / "ccr")], capsys,
            "holds committed results", "--force")
    refused(tables, ["--lam", "30", "--penalty", "1", "--out", str(results / "search")],
            capsys, "--force")
    refused(budgets, ["--out", str(results / "search")], capsys, "--force")
    refused(budgets, ["--quick", "--out", str(results / "search" / "sub")], capsys,
            "inside the committed results", "--force")
    assert not (results / "search" / "sub").exists()


def test_quick_mode_needs_its_own_out(search, tables, budgets, tmp_path, capsys, monkeypatch):
    """Quick numbers never land in the folder a real run of the experiment uses by default
    (``runs/...``): all three refuse ``--quick`` without ``--out``, and create nothing."""
    monkeypatch.chdir(tmp_path)
    refused(search, ["--variant", "ccr", "--quick"], capsys, "--quick needs --out")
    refused(budgets, ["--quick"], capsys, "--quick needs --out")
    refused(tables, ["--quick"], capsys, "--quick needs --out")
    assert not (tmp_path / "runs").exists()


def test_tables_refuse_bad_input(tables, tmp_path, capsys, monkeypatch):
    out = str(tmp_path / "never")
    refused(tables, ["--quick", "--seeds", "1", "--out", out], capsys, "--seeds")
    refused(tables, ["--lam", "30", "--penalty", "1", "--seed-offset", "95", "--out", out],
            capsys, "selection seeds")
    refused(tables, ["--lam", "30", "--penalty", "1", "--seed-offset", "195", "--out", out],
            capsys, "budgets' seeds")
    refused(tables, ["--lam", "30", "--penalty", "1", "--steps", "1000", "--out", out],
            capsys, "ends before learning starts")
    monkeypatch.setattr(tables, "SEARCHES", tmp_path / "no-searches")
    refused(tables, ["--penalty", "1", "--out", out], capsys, "no ccr search result", "--lam",
            "--searches")
    refused(tables, ["--out", out], capsys, "no ccr search result", "give --lam; and no "
            "pessimistic search result", "give --penalty")
    # Without a selection to read, the command line's own problems still come first.
    afile = tmp_path / "afile"
    afile.write_text("")
    refused(tables, ["--out", str(afile)], capsys, "is a file")
    refused(tables, ["--seed-offset", "95", "--out", out], capsys, "selection seeds")
    refused(tables, ["--steps", "1000", "--out", out], capsys, "ends before learning starts")


def results_folder(path: Path, settings: dict, records: list[dict], cells: dict[str, str],
                   experiment: str = "python experiments/budgets.py") -> Path:
    """A made-up results folder: ``cells`` maps a file name to its content's label."""
    (path / "cells").mkdir(parents=True)
    (path / "invocations.json").write_text(json.dumps(
        {"experiment": experiment, "settings": settings, "invocations": records}))
    for name, label in cells.items():
        cell = {"algo": "iddpg", "settings": settings, "budget": 3_000_000, "label": label}
        (path / "cells" / name).write_text(json.dumps(cell))
    return path


def test_an_experiment_refuses_a_folder_of_another_experiment(search, budgets, tmp_path,
                                                               capsys):
    out = results_folder(tmp_path / "search", {"seeds": [100, 101]}, [], {},
                         experiment="python experiments/search.py")
    refused(budgets, ["--out", str(out)], capsys, "holds the results of python "
            "experiments/search.py, not python experiments/budgets.py")


def test_welch_marks_say_which_way_ccr_differs(tables):
    """A significant difference is marked with its direction; a non-significant one is not
    marked at all, whichever its sign."""
    marks = {"plain": {"significant": True, "difference": -0.1, "p": 0.01},
             "pessimistic": {"significant": True, "difference": 0.2, "p": 0.02}}
    assert importlib.import_module("experiments.tables_report").welch_symbols(marks) == " ↓* ↑†"
    marks["plain"]["significant"] = False
    assert importlib.import_module("experiments.tables_report").welch_symbols(marks) == " ↑†"
    assert importlib.import_module("experiments.tables_report").welch_symbols({}) == ""


def test_an_out_that_is_a_file_is_refused(search, tmp_path, capsys):
    afile = tmp_path / "notes.md"
    afile.write_text("x")
    refused(search, ["--variant", "ccr", "--out", str(afile)], capsys, "is a file")
    refused(search, ["--variant", "ccr", "--out", str(afile / "below")], capsys,
            "cannot be created")


def test_a_search_never_trains_over_the_other_searchs_or_other_settings_cells(
        search, tmp_path, capsys):
    """The two searches share a program and cell names: a lambda search into the penalty
    search's folder is refused whatever the flags; cells made with other settings are only
    trained over with --force."""
    command = "python experiments/search.py"
    penalty = results_folder(tmp_path / "pessimistic", {"variant": "pessimistic"}, [], {},
                             experiment=command)
    for flags in ([], ["--force"]):
        refused(search, ["--variant", "ccr", "--out", str(penalty), *flags], capsys,
                "holds the pessimistic search's results")
    other = results_folder(tmp_path / "other", {"variant": "ccr", "seeds": [100, 101]}, [], {},
                           experiment=command)
    refused(search, ["--variant", "ccr", "--out", str(other)], capsys,
            "cells made with other settings", "--force")


def test_only_the_protocols_selection_feeds_the_tables(search, tables, tmp_path, capsys,
                                                       monkeypatch):
    """A selection over fewer than the 9 pairs (or at other settings) is provisional, and
    the tables refuse it."""
    full = search.Settings(variant="ccr", values=(0.3, 1.0, 3.0, 10.0, 30.0, 100.0))
    assert search.not_the_protocols(full) is None
    narrow = dataclasses.replace(full, algos=("iddpg", "maddpg"))
    assert "3 of 9 pairs not summarised" in search.not_the_protocols(narrow)
    quick = dataclasses.replace(full, quick=True, seeds=(100, 101))
    assert "the quick mode" in search.not_the_protocols(quick)
    assert "seeds" in search.not_the_protocols(quick)
    # The protocol's longer budget (its amendment of 2026-11-27) is the protocol's too;
    # another --steps is not.
    assert search.not_the_protocols(dataclasses.replace(full, steps=6_000_000)) is None
    assert "--steps 1000000" in search.not_the_protocols(
        dataclasses.replace(full, steps=1_000_000))
    # The on-policy family (amendment of 2026-12-02): its own 6 pairs, at its own budget.
    on_policy = dataclasses.replace(full, algos=("ippo", "mappo"))
    assert search.not_the_protocols(on_policy) is None
    monkeypatch.setattr(search.protocol, "ON_POLICY_BUDGET", 2_000_000)  # another budget
    assert "--steps 3000000" in search.not_the_protocols(
        dataclasses.replace(on_policy, steps=3_000_000))
    assert "3 of 6 pairs not summarised" in search.not_the_protocols(
        dataclasses.replace(on_policy, algos=("ippo",)))
    assert "--steps 1000000" in search.not_the_protocols(
        dataclasses.replace(on_policy, steps=1_000_000))
    assert "no Lagrangian for the on-policy" in search.not_the_protocols(
        dataclasses.replace(on_policy, variant="lagrangian"))
    monkeypatch.undo()
    # The Lagrangian (addition of 2026-12-03): its amendment's 2M over the tables' pairs,
    # the study's budget (the protocol's 3M) over the study's pairs, each by default.
    limits = search.protocol.COST_LIMITS
    tables_pairs = search.settings_from(search.build_parser().parse_args(
        ["--variant", "lagrangian"]))
    study_pairs = search.settings_from(search.build_parser().parse_args(
        ["--variant", "lagrangian", "--algos", "maddpg", "--scenarios", "hidden_obstacle",
         "turbulence"]))
    assert (tables_pairs.steps, study_pairs.steps) == (2_000_000, None)
    assert study_pairs.budget("maddpg") == 3_000_000
    assert search.not_the_protocols(tables_pairs) is None
    assert search.not_the_protocols(study_pairs) is None
    assert "--steps 2000000" in search.not_the_protocols(
        dataclasses.replace(study_pairs, steps=2_000_000))
    assert "--steps 3000000" in search.not_the_protocols(
        dataclasses.replace(tables_pairs, steps=3_000_000))
    assert tables_pairs.values == study_pairs.values == tuple(limits)
    searches = tmp_path / "searches"
    for variant, protocol_choice in (("ccr", False), ("pessimistic", True)):
        (searches / variant).mkdir(parents=True)
        (searches / variant / "search.json").write_text(json.dumps({"selection": {
            "value": 3.0, "protocol": protocol_choice,
            "provisional_because": "3 of 9 pairs not summarised"},
            "budgets": {algo: tables.protocol.budget(algo, None) for algo in tables.ALGOS}}))
    monkeypatch.setattr(tables, "SEARCHES", searches)
    refused(tables, ["--out", str(tmp_path / "never")], capsys, "not the protocol's choice",
            "3 of 9 pairs not summarised", "--lam")
    # A researcher's own searches (make sweep, make penalty-sweep) feed the tables through
    # --searches; the committed ones are the default.
    monkeypatch.undo()
    refused(tables, ["--searches", str(searches), "--out", str(tmp_path / "never")], capsys,
            "not the protocol's choice", str(searches / "ccr"))
    assert tables.selected("pessimistic", None, False, searches) == (
        3.0, f"selected by the search in {searches / 'pessimistic'}")
    # One inside the repository is named relative to it, never by this machine's path.
    inside = tables.RESULTS / "search" / ".." / "search"  # the committed one, spelt apart
    assert tables.selected("pessimistic", None, False, inside)[1].startswith(
        "selected by the search in experiments/results/search/pessimistic")
    # A choice by the fallback says so; a search at budgets the protocol no longer has is
    # refused (its own flag was written when it ran).
    record = json.loads((searches / "pessimistic" / "search.json").read_text())
    record["selection"]["fallback"] = True
    (searches / "pessimistic" / "search.json").write_text(json.dumps(record))
    assert tables.selected("pessimistic", None, False, searches)[1].endswith(
        "(its fallback: no value met the rule)")
    record["budgets"]["maac"] = 1_000_000
    (searches / "pessimistic" / "search.json").write_text(json.dumps(record))
    with pytest.raises(tables.cli.UsageError, match="not these tables' .* run it again"):
        tables.selected("pessimistic", None, False, searches)
    # Tables at the longer budget take only searches made at it, and the way round.
    record["budgets"] = {algo: 6_000_000 for algo in tables.ALGOS}
    (searches / "pessimistic" / "search.json").write_text(json.dumps(record))
    assert tables.selected("pessimistic", None, False, searches, 6_000_000)[0] == 3.0
    with pytest.raises(tables.cli.UsageError, match="not these tables' .* --searches"):
        tables.selected("pessimistic", None, False, searches)
    with pytest.raises(tables.cli.UsageError, match="not these tables'"):
        tables.selected("pessimistic", None, False, searches, 4_500_000)
    # --quick takes named (quick) searches' provisional choices, else its fixed values.
    assert tables.selected("ccr", None, True, searches) == (
        3.0, f"the provisional choice of the search in {searches / 'ccr'}")
    assert tables.selected("ccr", None, True) == (30.0, "the quick mode's fixed value")
    refused(tables, ["--quick", "--searches", str(tmp_path / "none"), "--out",
                     str(tmp_path / "never")], capsys, "no ccr search result")


def test_the_lambda_search_also_selects_against_the_exact_plain_runs(search):
    """Made-up rows over one pair and two seeds: against lambda 0's success (0.9) only
    lambda 2 is within 5 points; against the exact plain runs' (0.88), lambda 1 is too, and
    its lower danger wins."""
    def row(value, success, danger):
        return {"value": value, **{m: {"per_seed": [x, x]} for m, x in (
            ("success_rate", success), ("danger_frequency", danger), ("return", -30.0),
            ("target_distance", 0.1), ("hazard_distance", 0.5))}}

    settings = search.Settings(variant="ccr", values=(1.0, 2.0), seeds=(100, 101))
    cells = {("turbulence", "iddpg"): {"rows": [row(0.0, 0.9, 0.4), row(1.0, 0.84, 0.1),
                                                row(2.0, 0.88, 0.2)]}}
    exact = {("turbulence", "iddpg"): {"rows": [row(0.0, 0.88, 0.4)]}}
    assert search.selection(settings, cells)["value"] == 2.0
    assert search.selection(settings, cells, exact)["value"] == 1.0


@pytest.mark.parametrize("argv, fragments", [
    (["--seed-offset", "0"], ("overlaps the tables' seeds 0-9",)),
    (["--seed-offset", "99"], ("overlaps the selection seeds 100-102",)),
    (["--seeds", "1"], ("--seeds",)),
    (["--reach", "-1"], ("--reach",)),
    (["--lam", "-2"], ("--lam",)),
    (["--steps", "20000"], ("(--steps) 20,000 ends before learning",)),
    (["--figure", "/no/such/folder/f.png"], ("--figure",)),
    (["--figure", "figure.xyz"], ("--figure", ".png")),
])
def test_the_behaviour_exploration_refuses_bad_input_and_the_protocols_seeds(argv, fragments,
                                                                              capsys):
    refused(load("behaviour"), argv, capsys, *fragments)


@pytest.mark.parametrize("script, argv, fragments", [
    ("ccr_signal", ["--episodes", "0"], ("--episodes",)),
    ("ccr_signal", ["--train-steps", "200000"], ("--train-steps applies only with --trained",)),
    ("ccr_signal", ["--trained", "maddpg", "--train-steps", "20000"],
     ("(--steps) 20,000 ends before learning",)),
    ("ccr_signal", ["--matmul", "bf16"], ("--matmul",)),
    ("sanity", ["--steps", "1000"], ("(--steps) 1,000 ends before learning",)),
    ("sanity", ["--eval-episodes", "0"], ("--eval-episodes",)),
    ("sanity", ["--algos", "ppo"], ("--algos",)),
    ("calibrate", ["--episodes", "0"], ("--episodes",)),
    ("calibrate", ["--seed", "x"], ("--seed",)),
])
def test_the_measurement_scripts_refuse_bad_input_in_one_line(script, argv, fragments, capsys,
                                                              tmp_path):
    out = tmp_path / "never"
    writes = script != "sanity"  # sanity.py prints, it has no --out
    refused(load(script), [*argv, *(["--out", str(out)] if writes else [])], capsys, *fragments)
    assert not out.exists()  # refused before its folder was made


def test_the_measurement_scripts_replace_committed_results_only_with_force(
        tmp_path, capsys, monkeypatch):
    from experiments import ledger

    results = tmp_path / "results"
    for name in ("ccr_signal", "calibration"):
        (results / name).mkdir(parents=True)
        (results / name / "kept.md").write_text("committed")
    monkeypatch.setattr(ledger, "RESULTS", results)
    refused(load("ccr_signal"), ["--out", str(results / "ccr_signal")], capsys,
            "holds committed results", "--force")
    refused(load("calibrate"), ["--out", str(results / "calibration")], capsys,
            "holds committed results", "--force")
    afile = tmp_path / "afile"
    afile.write_text("")
    refused(load("ccr_signal"), ["--out", str(afile / "sub")], capsys, "cannot be created")
    refused(load("calibrate"), ["--out", str(afile)], capsys, "is a file")


def test_the_exact_plain_runs_are_taken_only_from_the_penalty_searchs_matching_cells(
        search, tmp_path):
    """Beside ``<out>`` = ``.../ccr``, ``.../pessimistic`` holds a penalty cell made with the
    same seeds and budget: it is used; one made with another budget is not."""
    settings = search.Settings(variant="ccr", values=(0.3, 1.0, 3.0, 10.0, 30.0, 100.0))
    penalty = dataclasses.replace(settings, variant="pessimistic",
                                  values=(0.03, 0.1, 0.3, 1.0, 3.0, 10.0))
    cells = {("turbulence", "iddpg"): {}}
    (tmp_path / "pessimistic" / "cells").mkdir(parents=True)
    path = tmp_path / "pessimistic" / "cells" / "turbulence-iddpg.json"
    from experiments.cell_identity import settings_record

    cell = {"algo": "iddpg", "settings": settings_record(penalty),
            "budget": 3_000_000, "rows": []}
    path.write_text(json.dumps(cell))
    found = search.exact_plain_cells(settings, tmp_path / "ccr", cells)
    assert found == {("turbulence", "iddpg"): cell}
    path.write_text(json.dumps({**cell, "budget": 2_000_000}))
    assert search.exact_plain_cells(settings, tmp_path / "ccr", cells) is None
    pessimistic_search = dataclasses.replace(settings, variant="pessimistic")
    assert search.exact_plain_cells(pessimistic_search, tmp_path / "ccr", cells) is None


def test_tf32_emulation_rounds_the_models_products_and_only_inside(tmp_path):
    """``ccr_signal.py --matmul tf32``: operands keep 10 mantissa bits, rounded to nearest
    with ties to even, and only CCR's model's products see them, only within the context."""
    import jax.numpy as jnp

    from ccrjax.transforms.ccr import dynamics, transform

    signal = load("ccr_signal")
    ulp = 2.0**-10  # TensorFloat32's spacing just above 1
    values = jnp.array([1.0 + ulp, 1.0 + ulp / 4, 1.0 + ulp / 2, 1.0 + 1.5 * ulp,
                        -(1.0 + 0.75 * ulp), 3.0e-20])
    rounded = np.asarray(signal.round_to_tf32(values))
    expected = [1.0 + ulp, 1.0, 1.0, 1.0 + 2 * ulp, -(1.0 + ulp)]
    np.testing.assert_array_equal(rounded[:5], np.float32(expected))
    assert abs(rounded[5] / 3.0e-20 - 1.0) <= 2.0**-11  # relative, at any magnitude

    a, b = jnp.full((1, 3), 1.0 + ulp / 4), jnp.ones((3, 1))
    exact = float(jnp.einsum("ij,jk->ik", a, b)[0, 0])
    with signal.tf32_model_products():
        assert float(dynamics.jnp.einsum("ij,jk->ik", a, b)[0, 0]) == 3.0
        assert float(transform.jnp.einsum("ij,jk->ik", a, b)[0, 0]) == 3.0
        assert float(jnp.einsum("ij,jk->ik", a, b)[0, 0]) == exact  # elsewhere untouched
    assert dynamics.jnp is jnp and transform.jnp is jnp
    assert exact != 3.0


def test_forewarning_counts_the_spells_a_teammates_danger_preceded():
    """Three robots, one episode of 6 steps. Robot 0 leads (danger at 1-2, nobody before
    it) and is in danger again at 5, after robot 1's spell at 3-4 (robot 0 safe and warned
    at 3-4); robot 1, within range of robot 0, is warned at 1-2; robot 2, out of range of
    both, is in danger at 4. Forewarned: robot 1's two steps and robot 0's step 5, 3 of 6,
    each led by 2 steps."""
    signal = load("ccr_signal")
    danger = np.zeros((6, 3, 1), bool)
    danger[[1, 2, 5], 0, 0] = True
    danger[[3, 4], 1, 0] = True
    danger[4, 2, 0] = True
    distance = np.full((6, 3, 3, 1), 0.5)
    distance[:, 2, :, 0] = distance[:, :, 2, 0] = 5.0  # robot 2 out of range of both
    distance[:, np.arange(3), np.arange(3)] = np.inf
    lead = signal.forewarning(danger, distance, comm_range=1.0, window=4)
    expected_lead = np.zeros((6, 3, 1), int)
    expected_lead[3, 1, 0] = expected_lead[5, 0, 0] = 2
    np.testing.assert_array_equal(lead, expected_lead)
    expected = np.zeros_like(danger)
    expected[[3, 4], 1, 0] = expected[5, 0, 0] = True
    np.testing.assert_array_equal(signal.forewarned_steps(danger, lead, 1), expected)
    np.testing.assert_array_equal(signal.forewarned_steps(danger, lead, 2), expected)
    assert not signal.forewarned_steps(danger, lead, 3).any()
    assert not signal.forewarning(danger, distance, comm_range=0.4, window=4).any()


def test_a_stale_warning_or_one_while_in_danger_does_not_forewarn():
    """Two robots in range, 12 steps. Both are in danger at 0-1 (a warning while in danger
    is none); robot 1 again at 6-7, while robot 0 is safe and so warned; robot 0 again at 9
    (its warning, 6-7, ended 1 step before 8: fresh within a window of 4, lead 9 - 6 = 3);
    robot 1 again at 11 (warned at 9, lead 2). With a window of 0 both warnings are stale."""
    signal = load("ccr_signal")
    danger = np.zeros((12, 2, 1), bool)
    danger[[0, 1, 9], 0, 0] = True
    danger[[0, 1, 6, 7, 11], 1, 0] = True
    distance = np.full((12, 2, 2, 1), 0.5)
    distance[:, [0, 1], [0, 1]] = np.inf
    lead = signal.forewarning(danger, distance, comm_range=1.0, window=4)
    assert lead[0].sum() == 0  # together at the start: nobody forewarned
    assert lead[6, 1, 0] == 0  # robot 1 was warned only while in danger itself (0-1)
    assert lead[9, 0, 0] == 3  # robot 0 warned at 6-7 while safe
    assert lead[11, 1, 0] == 2  # robot 1 warned at 9 while safe, ended 1 step before 10
    stale = signal.forewarning(danger, distance, comm_range=1.0, window=0)
    assert stale[9, 0, 0] == 0  # the warning ended at 7: more than 0 steps before 8
    assert stale[11, 1, 0] == 0


def test_a_cell_made_with_other_training_parameters_is_not_current(search, budgets, tables):
    """Each cell stores what its runs were trained with beyond the settings (learner,
    environment, transform); read back, it must equal what the current code would use for
    the same settings, in every experiment and variant, or the cell is trained again. A
    MAAC cell made with the MPE's five actions is not current for box9; a cell made before
    the record was stored is judged by its settings alone."""
    from experiments import cell_identity

    for quick in (False, True):
        made = [(search.Settings(variant=variant, values=(1.0,), quick=quick),
                 lambda s, sc, a: s.config(sc, a)) for variant in ("ccr", "pessimistic")]
        made.append((budgets.Settings(quick=quick), lambda s, sc, a: s.config(sc, a)))
        made += [(tables.Settings(lam=3.0, penalty=0.3, quick=quick),
                  lambda s, sc, a, v=v: s.config(sc, a, v))
                 for v in ("plain", "pessimistic", "ccr")]
        for settings, config_of in made:
            record = cell_identity.settings_record(settings)
            for scenario, algo in (("hidden_obstacle", "maac"), ("turbulence", "iddpg")):
                config = config_of(settings, scenario, algo)
                cell = {"scenario": scenario, "algo": algo, "settings": record,
                        "budget": settings.budget(algo),
                        "training": cell_identity.training_record(config)}
                if isinstance(settings, tables.Settings):
                    cell["variant"] = config.variant
                assert cell_identity.cell_is_current(cell, record), (settings, scenario, algo)

    settings = search.Settings(variant="ccr", values=(1.0,))
    record = cell_identity.settings_record(settings)
    config = settings.config("hidden_obstacle", "maac")
    training = cell_identity.training_record(config)
    assert training["learner"]["action_set"] == "box9"
    assert "lam" not in training["transform"] and training["transform"]["window"] == 4
    cell = {"scenario": "hidden_obstacle", "algo": "maac", "settings": record,
            "budget": settings.budget("maac"), "training": training}
    mpe5 = {**training, "learner": {**training["learner"], "action_set": "mpe5"}}
    assert not cell_identity.cell_is_current({**cell, "training": mpe5}, record)
    harder = {**training, "scenario": {**training["scenario"], "thickness": 0.5}}
    assert not cell_identity.cell_is_current({**cell, "training": harder}, record)
    legacy = {k: v for k, v in cell.items() if k != "training"}
    assert cell_identity.cell_is_current(legacy, record)


def test_every_experiment_trains_maac_at_the_protocols_update_settings(search, budgets,
                                                                        tables):
    """MAAC's protocol settings (1 update of batch 256 every 100 steps, docs/protocol.md's
    amendment of 2026-11-25) reach the budgets, both searches and every variant of the
    tables, and a MAAC cell made at the original's 4 x 1024 is not current; the DDPG
    family keeps its defaults."""
    from experiments import cell_identity, protocol

    made = [(budgets.Settings(), lambda s, sc, a: s.config(sc, a))]
    made += [(search.Settings(variant=variant, values=(1.0,)),
              lambda s, sc, a: s.config(sc, a)) for variant in ("ccr", "pessimistic")]
    made += [(tables.Settings(lam=3.0, penalty=0.3), lambda s, sc, a, v=v: s.config(sc, a, v))
             for v in ("plain", "pessimistic", "ccr")]
    for settings, config_of in made:
        maac = config_of(settings, "strong_wind", "maac").resolved_learner
        assert (maac.gradient_steps, maac.batch_size, maac.update_every) == (1, 256, 100)
        assert maac == protocol.LEARNERS["maac"]
        assert config_of(settings, "strong_wind", "maddpg").resolved_learner == DDPGConfig()
        record = cell_identity.settings_record(settings)
        config = config_of(settings, "strong_wind", "maac")
        training = cell_identity.training_record(config)
        cell = {"scenario": "strong_wind", "algo": "maac", "settings": record,
                "budget": settings.budget("maac"), "training": training,
                "variant": config.variant}
        assert cell_identity.cell_is_current(cell, record)
        original = {**training, "learner": {**training["learner"], "gradient_steps": 4,
                                            "batch_size": 1024}}
        assert not cell_identity.cell_is_current({**cell, "training": original}, record)


@pytest.mark.parametrize("name", ["budgets", "search", "tables", "results_report", "calibrate",
                                  "ccr_signal", "ccrjax.train", "ccrjax.sweep",
                                  "ccrjax.evaluate", "ccrjax.demo"])
def test_help_is_plain_text_with_every_option_explained(name):
    """``--help`` has a line for every option, no docstring markup (double backticks,
    Sphinx roles) and no path of this checkout."""
    module = importlib.import_module(name) if name.startswith("ccrjax.") else load(name)
    parser = module.build_parser()
    text = parser.format_help()
    for action in parser._actions:
        assert action.help, f"{name}: {action.option_strings or action.dest} has no help"
    assert "``" not in text and not re.search(r":[a-z]+:`", text), text
    assert str(EXPERIMENTS.parent) not in text, text


def test_an_experiment_stopped_by_ctrl_c_says_what_it_kept_in_one_line(tmp_path,
                                                                        subprocess_env):
    """Ctrl-C once the program is planned (compiling or training): status 130 and one line
    saying what was kept, no traceback; the invocation is recorded as stopped."""
    out = tmp_path / "search"
    process = subprocess.Popen(
        [sys.executable, str(EXPERIMENTS / "search.py"), "--variant", "pessimistic", "--quick",
         "--scenarios", "turbulence", "--algos", "iddpg", "--out", str(out)],
        stderr=subprocess.PIPE, text=True, env=subprocess_env)
    seen = []
    for line in process.stderr:
        seen.append(line)
        if "to train" in line:
            break
    process.send_signal(signal.SIGINT)
    rest = process.communicate(timeout=120)[1]
    assert process.returncode == 130, "".join(seen) + rest
    assert "Traceback" not in rest, rest
    # Heard at once, even if the program was compiling: one line says what was kept.
    assert rest.strip().splitlines()[-1].startswith(
        "python experiments/search.py: stopped by SIGINT; the finished programs' cells are "
        "kept")
    invocations = json.loads((out / "invocations.json").read_text())
    assert invocations["invocations"][-1]["finished"] is False


def test_a_run_whose_updates_go_non_finite_is_kept_named_and_reported(tmp_path, capsys):
    """The experiments keep such a run (the program skipped its non-finite updates and
    trained on from the last finite state): the grid names it, the log says so, and the
    summaries' sentence lists it."""
    from ccrjax.agents.ddpg import DDPGConfig
    from ccrjax.run.sweep_grid import nonfinite_runs, nonfinite_text
    from ccrjax.training import TrainConfig
    from ccrjax.training.grid import GridTraining
    from experiments import ledger

    exploding = TrainConfig(  # Adam steps of 1e38: the first update's parameters overflow
        algo="iddpg", scenario="strong_wind", variant="ccr", num_envs=2, episode_length=10,
        total_env_steps=120, eval_every=40, eval_episodes=3, learning_starts=40,
        learner=DDPGConfig(batch_size=16, actor_hidden=(8,), critic_hidden=(8,),
                           update_every=10, actor_lr=1e38, critic_lr=1e38))
    training = GridTraining(exploding, [3, 4], {"lam": [0.0, 30.0]})
    runs = ledger.Partial(tmp_path, minutes=1e6).train(training, "exploding")
    assert runs.nonfinite_iteration.tolist() == [1, 1]  # iteration 0 only fills the buffer
    assert np.all(np.isfinite(runs.history["return"]))  # evaluated, from finite parameters
    assert "2 of the 2 runs had non-finite updates, skipped (the learner kept its last " \
        "finite state and trained on; docs/protocol.md): exploding, seed 3, from iteration 1; " \
        "exploding, seed 4, from iteration 1." in capsys.readouterr().err
    assert runs.select(np.array([False, True])).nonfinite_iteration.tolist() == [1]
    # What the summaries say, for a search's cell, a table's, and one stored before.
    search_cell = {"parameter": "lam", "grid_seeds": [100, 101, 100, 101],
                   "grid_values": [0.0, 0.0, 3.0, 3.0], "nonfinite_iteration": [-1, -1, -1, 7]}
    table_cell = {"seeds": [0, 1], "nonfinite_iteration": [-1, -1]}
    assert nonfinite_runs(search_cell, "wind, MADDPG") == [
        "wind, MADDPG, lam 3, seed 101, from iteration 7"]
    assert nonfinite_runs(table_cell, "x") == []
    assert nonfinite_runs({"seeds": [0, 1]}, "x") == []  # made before: all finite
    assert nonfinite_text([], "the 4 runs") == "Every update of the 4 runs stayed finite."
    text = nonfinite_text(["wind, MADDPG, lam 3, seed 101, from iteration 7"],
                                 "the 4 runs")
    assert text.startswith("1 of the 4 runs had non-finite updates, skipped")
    assert text.endswith("wind, MADDPG, lam 3, seed 101, from iteration 7.")


def test_invocations_in_one_folder_at_once_keep_each_others_records(search, tmp_path):
    """Two invocations working in one folder at once (lanes of a grid side by side): every
    update of one keeps the other's record, each in the place it began, and its own scope
    (the file's settings are the cells' alone, whoever wrote last)."""
    from experiments import cell_identity, ledger

    def settings(*extra: str):
        return search.settings_from(search.build_parser().parse_args(
            ["--variant", "pessimistic", "--quick", *extra]))

    first = ledger.Ledger(tmp_path, settings("--algos", "iddpg"), "first", "search")
    first.record(0)
    second = ledger.Ledger(tmp_path, settings("--algos", "maac"), "second", "search")
    second.record(0)
    first.record(1, finished=True)  # written from a view that began before the second
    second.record(1)
    written = json.loads((tmp_path / "invocations.json").read_text())
    records = written["invocations"]
    assert [(r["command"], r["finished"]) for r in records] == [("first", True),
                                                                 ("second", False)]
    assert [r["scope"]["algos"] for r in records] == [["iddpg"], ["maac"]]
    assert written["settings"] == cell_identity.folder_settings(
        cell_identity.settings_record(settings()))
    assert not set(cell_identity.NOT_IN_CELLS) & set(written["settings"])
    assert [r["command"] for r in first.invocations] == ["first", "second"]


def test_a_stopped_invocation_shows_only_the_time_it_recorded(search):
    """A record's time is rewritten as each program finishes: a stopped invocation is shown
    with the programs it finished and the time to the last; before the first, with none."""
    from experiments import ledger
    run = {"command": "python experiments/search.py", "commit": "abc", "device": "cpu",
           "jax": "0.4", "date": "2026-11-28 03:00 UTC", "wall_time_s": 0.05}
    finished = ledger.invocation_line({**run, "finished": True, "programs_trained": 2,
                                       "wall_time_s": 4861.0}, 18)
    assert finished.endswith("trained 2 of 18 program(s) in 1h21m")
    part = ledger.invocation_line({**run, "finished": False, "programs_trained": 1,
                                   "wall_time_s": 75.0})
    assert part.endswith("stopped before the end, after it trained 1 program(s) in 1m15s")
    none = ledger.invocation_line({**run, "finished": False, "programs_trained": 0})
    assert none.endswith("stopped before the end, before its first program finished")
    assert "0m00s" not in none


