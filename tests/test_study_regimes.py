"""The study's regimes as settings of the experiments (docs/protocol.md, amendment of
2026-12-01 and its addition of 2026-12-02): ``protocol.REGIMES`` holds what the reference
controllers chose, every run of a regime is whole iterations, the tables' regime leaves
the records of the paper's experiments as they were, and the budgets run states a regime's
budget by the rule the amendment names."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments import budgets, protocol, regimes
from experiments.ledger import expected_training, settings_record

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


def test_a_regimes_budget_is_the_smallest_candidate_where_every_study_pair_levels_off():
    """Made-up checks: in `column` the rule runs over the study's pairs alone (a cell of
    another pair, here MADDPG in the wind, does not move it)."""
    def cell(scenario: str, passes: dict[int, bool]) -> dict:
        return {"scenario": scenario, "algo": "maddpg", "checks": [
            {"budget": b, "plateaued": p, "last": 1.0, "previous": 0.5}
            for b, p in passes.items()]}

    settings = {"candidate_budgets": [1_200_000, 2_400_000, 3_000_000], "regime": "column"}
    cells = [cell("hidden_obstacle", {1_200_000: True, 2_400_000: True, 3_000_000: True}),
             cell("turbulence", {1_200_000: False, 2_400_000: True, 3_000_000: True}),
             cell("strong_wind", {1_200_000: False, 2_400_000: False, 3_000_000: False})]
    text = "\n".join(budgets.rule_lines({"cells": cells, "settings": settings}))
    assert "The `column` regime's budget (the smallest" in text
    assert "**2,400,000** steps." in text
    assert "not yet, 1 of the 2" in "\n".join(
        budgets.rule_lines({"cells": cells[:1], "settings": settings}))
    for check in cells[1]["checks"]:
        check["plateaued"] = False
    assert ("no candidate passes for every plain learner, so **3,000,000** steps, flagged: "
            "at it the check fails for turbulence-maddpg") in "\n".join(
        budgets.rule_lines({"cells": cells, "settings": settings}))
