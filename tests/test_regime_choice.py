"""``experiments/regimes.py``'s choice of the study's regime per scenario, on made-up rows."""

from __future__ import annotations

from experiments import calibrate, regimes
from tests.test_train_command import assert_usage_error, run_main


def regime(scenario, spacing, own, team, own_success=0.9, team_success=0.9, memoriser=0.1,
           oracle=0.0):
    rows = {
        "self_reactive": {"danger_frequency": own, "success_rate": own_success},
        "team_informed": {"danger_frequency": team, "success_rate": team_success},
        "oracle": {"danger_frequency": oracle, "success_rate": 1.0},
        "memoriser": {"danger_frequency": memoriser, "success_rate": 0.9},
    }
    return {"scenario": scenario, "placement": 1.0, "formation": "column",
            "column_spacing": spacing, "arena_half_extent": [3.0, 2.0], "episode_length": 30,
            "rows": rows, **regimes.informative(rows)}


def test_an_informative_regime_is_chosen_before_any_closer_looking_one():
    grid = [regime("a", 0.3, own=0.20, team=0.12),  # ratio 0.6: not informative
            regime("a", 0.45, own=0.20, team=0.09),  # ratio 0.45: informative
            regime("a", 0.6, own=0.20, team=0.02, memoriser=0.01)]  # memoriser as safe
    chosen = regimes.choose_regimes(grid)["a"]
    assert chosen["informative"] and chosen["column_spacing"] == 0.45


def test_without_one_the_closest_keeps_the_other_conditions():
    grid = [regime("b", 0.3, own=0.20, team=0.15),  # ratio 0.75, conditions met
            regime("b", 0.45, own=0.20, team=0.12, team_success=0.8),  # unequal success
            regime("b", 0.6, own=0.20, team=0.14, memoriser=0.02),  # memoriser near oracle
            regime("b", 0.9, own=0.20, team=0.17)]  # ratio 0.85
    chosen = regimes.choose_regimes(grid)["b"]
    assert not chosen["informative"] and chosen["column_spacing"] == 0.3
    assert abs(chosen["danger_ratio"] - 0.75) < 1e-9
    # With no regime meeting the other conditions, the lowest ratio of all.
    only = regimes.choose_regimes(grid[1:3])["b"]
    assert only["column_spacing"] == 0.45


def test_a_regime_whose_self_reactive_robots_never_meet_danger_is_never_the_closest():
    grid = [regime("c", 0.3, own=0.0, team=0.0), regime("c", 0.6, own=0.2, team=0.18)]
    assert regimes.choose_regimes(grid)["c"]["column_spacing"] == 0.6


def test_calibrate_refuses_a_column_no_scenario_can_run_in_one_line(capsys, tmp_path):
    status, _, err = run_main(calibrate, ["--regimes", "--spacings", "0.1", "--out",
                                          tmp_path / "r"], capsys)
    assert_usage_error(status, err, "--spacings 0.1", "at least min_separation")
    assert not (tmp_path / "r").exists()
