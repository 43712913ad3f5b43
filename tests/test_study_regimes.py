"""The study's regimes as settings of the experiments (docs/protocol.md, amendment of
2026-12-01 and its addition of 2026-12-02): ``protocol.REGIMES`` holds what the reference
controllers chose, every run of a regime is whole iterations, the tables' regime leaves
the records of the paper's experiments as they were, and the budgets run states a regime's
budget by the rule the amendment names."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from experiments import budgets, budgets_report, protocol, regimes, search
from experiments.cell_identity import expected_training, settings_record

RESULTS = Path(__file__).resolve().parent.parent / "experiments" / "results"


def test_the_column_regime_is_the_one_the_reference_controllers_chose():
    grid = json.loads((RESULTS / "regimes" / "regimes.json").read_text())["grid"]
    chosen = regimes.choose_regimes(grid["regimes"])
    column = protocol.REGIMES["column"]
    for scenario in protocol.STUDY_SCENARIOS:
        made = chosen[scenario]
        layout = regimes.regime_layout(made["placement"], made["formation"],
                                       made["column_spacing"])
        assert column.episode_length == made["episode_length"]
        for name, value in column.layout_params.items():
            assert getattr(layout, name) == value, (scenario, name)


@pytest.mark.parametrize("algo", [*protocol.STUDY_ALGOS, *protocol.ON_POLICY_ALGOS])
@pytest.mark.parametrize("regime", list(protocol.REGIMES))
def test_every_regime_evaluates_and_ends_on_whole_iterations(regime, algo):
    """Each candidate budget at the regime's evaluation interval runs exactly as asked
    (run_config refuses anything rounded); 100,000 steps is not whole in the column."""
    spec = protocol.REGIMES[regime]
    for steps in spec.budget_candidates:
        settings = protocol.Settings(seeds=(200,), steps=steps, eval_every=spec.eval_every,
                                     regime=regime)
        config = protocol.run_config(settings, "turbulence", algo, "plain")
        assert config.episode_length == spec.episode_length
        assert config.layout.formation == spec.layout_params.get("formation", "abreast")
    if regime == "column":
        with pytest.raises(ValueError, match="whole evaluation intervals"):
            protocol.run_config(protocol.Settings(seeds=(200,), regime=regime),
                                "turbulence", algo, "plain")


def test_the_tables_regime_leaves_the_records_as_they_were_and_another_names_itself():
    today = protocol.Settings(seeds=(0, 1))
    assert "regime" not in settings_record(today)
    column = protocol.Settings(seeds=(0, 1), eval_every=120_000, regime="column")
    record = settings_record(column)
    assert record["regime"] == "column"
    cell = {"scenario": "hidden_obstacle", "algo": "maddpg", "variant": "plain"}
    assert expected_training(cell, record)["layout"]["formation"] == "column"
    assert expected_training(cell, record)["episode_length"] == 30
    assert expected_training(cell, settings_record(today))["layout"].get(
        "formation", "abreast") == "abreast"
    with pytest.raises(ValueError, match="--regime 'sideways'"):
        protocol.Settings(seeds=(0,), regime="sideways")


def test_the_column_budgets_run_checks_the_regimes_candidates():
    args = budgets.build_parser().parse_args(["--regime", "column", "--algos", "maddpg"])
    settings = budgets.settings_from(args)
    assert settings.seeds == protocol.BUDGET_SEEDS
    assert settings.eval_every == 120_000
    assert settings.candidates("maddpg") == [1_200_000, 2_400_000, 3_000_000]
    quick = budgets.settings_from(budgets.build_parser().parse_args(
        ["--regime", "column", "--quick"]))
    assert quick.config("turbulence", "maddpg").episode_length == 30  # a column needs 22


def test_a_regimes_budget_is_the_largest_of_the_study_pairs_proposals():
    """Made-up checks (addition of 2026-12-03): in `column` the budget is the largest of the
    study pairs' proposed budgets (each the smallest candidate from which on every check
    passes), so a check passed early by a return still rising (the obstacle's at 1.2M, which
    fails at 2.4M) does not choose it; another pair's cell (MADDPG in the wind) does not
    move it; a pair still moving at the end gives 3M, flagged."""
    def cell(scenario: str, passes: dict[int, bool]) -> dict:
        checks = [{"budget": b, "plateaued": p, "last": 1.0, "previous": 0.5}
                  for b, p in passes.items()]
        proposed = next((c["budget"] for i, c in enumerate(checks)
                         if all(d["plateaued"] for d in checks[i:])), None)
        return {"scenario": scenario, "algo": "maddpg", "checks": checks,
                "proposed_budget": proposed}

    settings = {"candidate_budgets": [1_200_000, 2_400_000, 3_000_000], "regime": "column"}
    cells = [cell("hidden_obstacle", {1_200_000: True, 2_400_000: False, 3_000_000: True}),
             cell("turbulence", {1_200_000: True, 2_400_000: True, 3_000_000: True}),
             cell("strong_wind", {1_200_000: False, 2_400_000: False, 3_000_000: False})]
    text = "\n".join(budgets_report.rule_lines({"cells": cells, "settings": settings}))
    assert "The `column` regime's budget (the largest of the study pairs' proposed" in text
    assert "**3,000,000** steps." in text
    cells[0] = cell("hidden_obstacle", {1_200_000: False, 2_400_000: True, 3_000_000: True})
    assert "**2,400,000** steps." in "\n".join(
        budgets_report.rule_lines({"cells": cells, "settings": settings}))
    assert "not yet, 1 of the 2" in "\n".join(
        budgets_report.rule_lines({"cells": cells[:1], "settings": settings}))
    cells[1] = cell("turbulence", {1_200_000: True, 2_400_000: True, 3_000_000: False})
    assert ("**3,000,000** steps, flagged: the return was still moving at the end for "
            "turbulence-maddpg") in "\n".join(
        budgets_report.rule_lines({"cells": cells, "settings": settings}))


def search_settings(**fields) -> search.Settings:
    variant = fields.pop("variant", "ccr")
    return search.Settings(variant=variant, values=protocol.SEARCHED[variant][1],
                           seeds=protocol.SELECTION_SEEDS, **fields)


STUDY = {"scenarios": protocol.STUDY_SCENARIOS, "algos": protocol.STUDY_ALGOS}


def test_a_search_is_the_protocols_over_the_tables_or_the_studys_pairs(monkeypatch):
    """In the tables' regime lambda and the penalty are chosen over the paper's 9 pairs or
    the study's; CCR's parts over the study's alone; in the column only at the budget its
    budgets run chose, at its own evaluation interval."""
    assert search.not_the_protocols(search_settings()) is None
    assert search.not_the_protocols(search_settings(variant="pessimistic", **STUDY)) is None
    assert search.not_the_protocols(search_settings(variant="ccr_reward", **STUDY)) is None
    why = search.not_the_protocols(search_settings(variant="ccr_perfect"))
    assert why.startswith("pairs outside the study's (hidden_obstacle-iddpg"), why
    why = search.not_the_protocols(search_settings(scenarios=("turbulence",), algos=("maddpg",)))
    assert why == "1 of 2 pairs not summarised (hidden_obstacle-maddpg)"

    column = {**STUDY, "regime": "column", "eval_every": 120_000}
    monkeypatch.setitem(protocol.REGIME_BUDGETS, "column", {})  # before its budgets run
    why = search.not_the_protocols(search_settings(**column))
    assert why == ("the column regime's budget of maddpg is not chosen yet "
                   "(experiments/budgets.py --regime column)")
    monkeypatch.setitem(protocol.REGIME_BUDGETS, "column", {"maddpg": 2_400_000})
    settings = search_settings(**column)
    assert settings.budget("maddpg") == 2_400_000
    # The runs train for the budget the cells record (the regime's, not today's 3M).
    assert settings.config("turbulence", "maddpg").total_env_steps == 2_400_000
    assert search.not_the_protocols(settings) is None
    assert search.not_the_protocols(search_settings(**column, steps=3_000_000)) == (
        "--steps 3000000")
    assert search.not_the_protocols(search_settings(**{**column, "eval_every": 240_000})) == (
        "other evaluations")


def test_the_studys_searches_default_to_its_pairs_and_the_regimes_evaluations():
    def parsed(*argv: str) -> search.Settings:
        return search.settings_from(search.build_parser().parse_args(["--variant", *argv]))

    part = parsed("ccr_reward")
    assert (part.scenarios, part.algos, part.regime) == (
        protocol.STUDY_SCENARIOS, protocol.STUDY_ALGOS, "today")
    column = parsed("pessimistic", "--regime", "column")
    assert (column.scenarios, column.eval_every) == (protocol.STUDY_SCENARIOS, 120_000)
    assert column.budget("maddpg") == 3_000_000  # the largest candidate until chosen
    assert parsed("ccr").scenarios == tuple(search.PAPER_SCENARIOS)
    assert parsed("lagrangian", "--regime", "column").steps is None
    quick = parsed("ccr_perfect", "--regime", "column", "--quick")
    assert quick.config("turbulence", "maddpg").episode_length == 30


def test_a_parts_lambda_search_takes_the_penalty_searchs_exact_plain_runs(tmp_path):
    settings = search_settings(variant="ccr_perfect", **STUDY)
    penalty = dataclasses.replace(settings, variant="pessimistic",
                                  values=protocol.SEARCHED["pessimistic"][1])
    cells = {pair: {} for pair in protocol.study_pairs(protocol.STUDY_ALGOS)}
    (tmp_path / "pessimistic" / "cells").mkdir(parents=True)
    for scenario, algo in cells:
        cell = {"algo": algo, "settings": settings_record(penalty), "budget": 3_000_000}
        (tmp_path / "pessimistic" / "cells" / f"{scenario}-{algo}.json").write_text(
            json.dumps(cell))
    assert set(search.exact_plain_cells(settings, tmp_path / "ccr_perfect", cells)) == set(cells)
    assert search.exact_plain_cells(dataclasses.replace(settings, variant="lagrangian"),
                                    tmp_path / "lagrangian", cells) is None
    # In today's regime, without a penalty search beside it, the committed tables' one
    # (which holds the study's pairs at 3M on the selection seeds); in another, none.
    found = search.exact_plain_cells(settings, tmp_path / "today" / "ccr_perfect", cells)
    assert set(found) == set(cells)
    assert all(cell["rows"][0]["value"] == 0.0 for cell in found.values())
    column = search_settings(variant="ccr_perfect", regime="column", eval_every=120_000, **STUDY)
    assert search.exact_plain_cells(column, tmp_path / "column" / "ccr_perfect", cells) is None


@pytest.mark.slow  # two quick pipelines: about 40 s
def test_the_column_budgets_and_a_parts_search_run_end_to_end(tmp_path):
    """At a toy size in the column: the budgets run and a search of CCR's perfect detector
    write their summaries, naming the regime, from cells trained in the column."""
    assert budgets.main(["--regime", "column", "--quick", "--algos", "maddpg", "--scenarios",
                         "turbulence", "--out", str(tmp_path / "budgets")]) == 0
    assert search.main(["--variant", "ccr_perfect", "--regime", "column", "--quick",
                        "--scenarios", "turbulence", "--out", str(tmp_path / "search")]) == 0
    for summary in (tmp_path / "budgets" / "budgets.md", tmp_path / "search" / "search.md"):
        text = summary.read_text()
        assert "regime `column`" in text and "30-step episodes" in text
    cell = json.loads((tmp_path / "search" / "cells" / "turbulence-maddpg.json").read_text())
    assert cell["settings"]["regime"] == "column"
    assert cell["training"]["layout"]["formation"] == "column"
