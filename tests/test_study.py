"""The study's command and measures (docs/protocol.md, amendment of 2026-12-01), on
made-up episodes and search cells: who the followers are and what is measured of them,
the forewarned share per seed, which value each variant trains with and what its cells
record, and what bad input gets."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ccrjax import cli
from experiments import protocol, study
from experiments import study_analysis as analysis
from experiments import study_report as report
from experiments.cell_identity import settings_record
from experiments.study_measures import cell_measures, follower_mask, followers


def column_episode() -> dict[str, np.ndarray]:
    """Three robots in a column along x for 4 steps, 2 episodes: robot 2 leads in the
    first, robot 0 in the second; the hazard's centre at the origin."""
    T, N, E = 4, 3, 2
    position = np.zeros((T + 1, N, 2, E))
    position[:, :, 0, 0] = np.array([-2.0, -1.5, -1.0])  # robot 2 furthest along x
    position[:, :, 0, 1] = np.array([-1.0, -2.0, -1.5])  # robot 0
    position[:, :, 1, :] = 1.0
    danger = np.zeros((T, N, E), bool)
    danger[1:3, 2, 0] = True  # the leader of episode 0, two steps
    danger[3, 1, 1] = True  # a follower of episode 1, one step
    success = np.array([[1, 0], [0, 1], [1, 1]], bool)
    centre = np.zeros((2, E))
    return {"position": position, "danger": danger, "success": success, "centre": centre}


def test_the_followers_are_all_but_the_robot_furthest_along_the_way():
    ep = column_episode()
    np.testing.assert_array_equal(follower_mask(ep["position"]),
                                  [[True, False], [True, True], [False, True]])
    got = followers(ep["position"], ep["danger"], ep["success"], ep["centre"])
    # Followers: robots 0, 1 (episode 0) and 1, 2 (episode 1).
    distance = np.mean([np.hypot(-2.0, 1.0), np.hypot(-1.5, 1.0), np.hypot(-2.0, 1.0),
                        np.hypot(-1.5, 1.0)])
    assert got["followers_centre_distance"] == pytest.approx(distance)
    assert got["followers_danger"] == pytest.approx(np.mean([0, 0, 0.25, 0]))
    assert got["followers_success"] == pytest.approx(np.mean([1, 0, 1, 1]))


def test_cell_measures_are_per_seed_and_a_seed_without_danger_has_no_forewarned_share():
    ep = column_episode()
    calm = {k: v.copy() for k, v in ep.items()}
    calm["danger"][:] = False
    episodes = {"position": np.stack([ep["position"], calm["position"]]),
                "danger": np.stack([ep["danger"], calm["danger"]]).astype(np.int32),
                "success": np.stack([ep["success"], calm["success"]]),
                "hazard_centre": np.stack([ep["centre"], calm["centre"]])}
    measures = cell_measures(episodes)
    assert measures["forewarned_share"][1] is None
    assert 0.0 <= measures["forewarned_share"][0] <= 1.0
    assert measures["followers_danger"] == pytest.approx([0.0625, 0.0])
    assert len(measures["followers_success"]) == 2


def test_a_programs_cells_record_only_their_own_value():
    settings = study.Settings(values={"pessimistic": 3.0, "ccr": 1.0, "ccr_perfect": 10.0},
                              regime="column", eval_every=120_000)
    assert settings.run_params("ccr_perfect") == {"lam": 10.0}
    assert settings.run_params("ccr_scores") == {}
    assert settings.for_program(("ccr",)).values == {"ccr": 1.0}
    assert settings.for_program(("plain", "pessimistic")).penalty == 3.0
    assert settings_record(settings.for_program(("danger_flags",)))["values"] == {}
    names = [job.name for job in study.jobs_of(settings, ("plain", "pessimistic", "ccr"))]
    assert names == ["hidden_obstacle-maddpg-plain+pessimistic", "hidden_obstacle-maddpg-ccr",
                     "turbulence-maddpg-plain+pessimistic", "turbulence-maddpg-ccr"]


def test_an_invocation_of_fewer_variants_keeps_the_folders_records(tmp_path):
    """``--variants`` narrows an invocation's values to the variants it trains: its cells
    are some of the folder's, so the earlier records stay and the folder keeps every
    variant's value; a variant trained with another value makes other cells, and the other
    variants' values stay (their cells do)."""
    from experiments import ledger

    def settings(**values: float):
        return study.Settings(values=values, regime="column", eval_every=120_000)

    whole = {"pessimistic": 3.0, "ccr": 10.0, "lagrangian": 0.1}
    ledger.Ledger(tmp_path, settings(**whole), "whole", "study").record(1, finished=True)
    narrow = ledger.Ledger(tmp_path, settings(ccr=10.0), "narrow", "study")
    narrow.record(1, finished=True)
    written = json.loads((tmp_path / "invocations.json").read_text())
    assert [r["command"] for r in written["invocations"]] == ["whole", "narrow"]
    assert written["settings"]["values"] == whole
    assert ledger.check_experiment(tmp_path, "study", settings_record(settings(ccr=10.0)),
                                   force=False) is None
    problem = ledger.check_experiment(tmp_path, "study", settings_record(settings(ccr=30.0)),
                                      force=False)
    assert problem is not None and "(values)" in problem
    other = ledger.Ledger(tmp_path, settings(ccr=30.0), "other value", "study")  # --force
    other.record(0)
    written = json.loads((tmp_path / "invocations.json").read_text())
    assert [r["command"] for r in written["invocations"]] == ["other value"]
    assert written["settings"]["values"] == {**whole, "ccr": 30.0}
    assert ledger.check_experiment(tmp_path, "study", settings_record(settings(pessimistic=1.0)),
                                   force=False) is not None


def search_cells(folder, regime: str, variant: str, danger: list[float]) -> None:
    """Made-up search cells of the study's pairs: value 0 and the six values, each seed
    the same metrics; ``danger`` per grid value, success always 0.9."""
    settings = study.search.Settings(
        variant=variant, values=protocol.SEARCHED[variant][1], regime=regime,
        eval_every=protocol.REGIMES[regime].eval_every, scenarios=protocol.STUDY_SCENARIOS,
        algos=protocol.STUDY_ALGOS)
    (folder / "cells").mkdir(parents=True)
    for scenario, algo in protocol.study_pairs(protocol.STUDY_ALGOS):
        rows = [{m: {"per_seed": [d if m == "danger_frequency" else 0.9] * 3}
                 for m in ("return", "success_rate", "target_distance", "danger_frequency",
                           "hazard_distance")} for d in danger]
        cell = {"scenario": scenario, "algo": algo, "settings": settings_record(settings),
                "budget": settings.budget(algo), "rows": rows}
        (folder / "cells" / f"{scenario}-{algo}.json").write_text(json.dumps(cell))


def test_the_value_is_the_regimes_search_choice_over_the_studys_pairs(tmp_path, monkeypatch):
    folder = tmp_path / "ccr_reward"
    search_cells(folder, "today", "ccr_reward", [0.3, 0.2, 0.1, 0.05, 0.2, 0.3, 0.3])
    assert study.chosen_value("ccr_reward", "today", ("maddpg",), folder) == 3.0
    with pytest.raises(cli.UsageError, match="needs its search's cells hidden_obstacle-maddpg"):
        study.chosen_value("ccr_perfect", "today", ("maddpg",), tmp_path / "none")
    # The Lagrangian's search of the study's pairs in today is at the study's budget (3M).
    search_cells(tmp_path / "lagrangian", "today", "lagrangian",
                 [0.3, 0.2, 0.1, 0.05, 0.2, 0.3, 0.3])
    assert study.chosen_value("lagrangian", "today", ("maddpg",),
                              tmp_path / "lagrangian") == 0.02
    column = tmp_path / "column" / "ccr"
    search_cells(column, "column", "ccr", [0.3, 0.2, 0.1, 0.05, 0.2, 0.3, 0.3])
    monkeypatch.setitem(protocol.REGIME_BUDGETS, "column", {})  # before its budgets run
    with pytest.raises(cli.UsageError, match="provisional .*budget of maddpg is not chosen"):
        study.chosen_value("ccr", "column", ("maddpg",), column)
    monkeypatch.setitem(protocol.REGIME_BUDGETS, "column", {"maddpg": 3_000_000})
    assert study.chosen_value("ccr", "column", ("maddpg",), column) == 3.0
    assert study.search_folder("ccr", "today", tmp_path) == study.TABLES_SEARCHES["ccr"]
    assert study.search_folder("ccr", "column", tmp_path) == tmp_path / "ccr"


@pytest.mark.parametrize("argv, fragment", [
    (["--regime", "column", "--value", "plain", "1"], "--value plain: not a searched variant"),
    (["--regime", "column", "--value", "ccr", "-1"], "--value ccr -1: give a finite number > 0"),
    (["--regime", "column", "--value", "ccr", "inf"], "give a finite number > 0"),
    (["--regime", "column", "--seeds", "4"], "--seeds"),
    (["--regime", "sideways"], "--regime"),
    (["--regime", "column", "--algos", "maddpg", "ippo"], "mixes the off-policy learners"),
    (["--regime", "column", "--variants", "pessimistic"],
     "--variants pessimistic needs its search's cells"),
])
def test_bad_input_is_one_line_before_anything_trains(argv, fragment, tmp_path, capsys):
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exit_:
        study.main([*argv, "--searches", str(tmp_path / "none"), "--out", str(out)])
    assert exit_.value.code == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line]
    assert len(lines) == 1 and fragment in lines[0], lines
    assert not out.exists()


@pytest.mark.slow  # eight quick programs: about 2 minutes
def test_the_study_runs_end_to_end_in_the_column_and_resumes_without_training(
        tmp_path, kill_grid_in_program):
    out = tmp_path / "study"
    argv = ["--regime", "column", "--quick", "--scenarios", "turbulence", "--out", str(out)]
    # Killed in its third program (one per call of run_grid): the record counts the two
    # programs the invocation finished, not only those of its last call.
    kill_grid_in_program(3)
    with pytest.raises(KeyboardInterrupt):
        study.main(argv)
    run = json.loads((out / "invocations.json").read_text())["invocations"][-1]
    assert (run["programs_trained"], run["finished"]) == (2, False)
    kill_grid_in_program(None)
    assert study.main(argv) == 0
    run = json.loads((out / "invocations.json").read_text())["invocations"][-1]
    assert (run["programs_trained"], run["finished"]) == (5, True)
    made = json.loads((out / "study_cells.json").read_text())
    assert all(made["programs"].values()) and len(made["programs"]) == 7
    for variant in study.VARIANTS:
        cell = json.loads((out / "cells" / f"turbulence-maddpg-{variant}.json").read_text())
        assert cell["training"]["layout"]["formation"] == "column"
        assert len(cell["measures"]["followers_success"]) == 2
    assert study.main([*argv, "--no-train"]) == 0
    # The report keeps every cell the protocol's (quick) study makes, and leaves none out.
    assert report.main(["--out", str(tmp_path), "--column", str(out)]) == 0
    text = (tmp_path / "study.md").read_text()
    assert "Left out" not in text and "| turbulence | MADDPG | lagrangian |" in text


def made_up(danger: list[float], success: float = 0.9) -> dict:
    """A study cell of 5 seeds with these dangers (success the same on every seed)."""
    seeds = len(danger)
    return {"final": {"danger_frequency": danger, "success_rate": [success] * seeds},
            "measures": {"forewarned_share": [0.5, None, 0.3, 0.4, 0.6][:seeds],
                         "followers_centre_distance": [1.0] * seeds,
                         "followers_danger": danger, "followers_success": [success] * seeds}}


SPREAD = np.array([-0.01, 0.0, 0.01, 0.005, -0.005])


def test_the_hypotheses_on_made_up_cells():
    """CCR no different from plain today, clearly safer in the column at the same success:
    H1, H2 and H3 hold; the perfect detector is safer than CCR; CCR's danger equals the
    penalty's. Then a CCR that costs 10 points of success fails H2, and a cell not made
    leaves its hypotheses open."""
    cells = {}
    for regime, plain, ccr in (("today", 0.30, 0.30), ("column", 0.30, 0.20)):
        for variant, level in (("plain", plain), ("ccr", ccr), ("pessimistic", ccr),
                               ("ccr_perfect", 0.10)):
            cells[(regime, "turbulence", "maddpg", variant)] = made_up(
                list(level + SPREAD))
    found = analysis.hypotheses(cells, "turbulence", "maddpg", resamples=500)
    assert found["H1"]["holds"] is True and found["H1"]["p"] > 0.05
    assert found["H2"]["holds"] is True and found["H2"]["p"] < 0.05
    assert found["H2"]["success_drop"] == pytest.approx(0.0)
    assert found["H3"]["holds"] is True
    assert found["H3"]["difference"] == pytest.approx(0.10)
    perfect = found["H4"]["column/ccr_perfect"]
    assert perfect["against_ccr"]["significant"] and perfect["against_ccr"]["difference"] < 0
    assert not found["H5"]["column/pessimistic"]["danger_frequency"]["significant"]
    assert "column/lagrangian" not in found["H5"]

    cells[("column", "turbulence", "maddpg", "ccr")] = made_up(list(0.20 + SPREAD), 0.80)
    assert analysis.hypotheses(cells, "turbulence", "maddpg", 500)["H2"]["holds"] is False
    del cells[("today", "turbulence", "maddpg", "plain")]
    found = analysis.hypotheses(cells, "turbulence", "maddpg", 500)
    assert found["H1"] == {"holds": None} and found["H3"] == {"holds": None}


def test_the_danger_is_no_lower_one_sidedly_when_ccr_is_worse():
    cells = {("column", "turbulence", "maddpg", "plain"): made_up(list(0.2 + SPREAD)),
             ("column", "turbulence", "maddpg", "ccr"): made_up(list(0.3 + SPREAD))}
    found = analysis.hypotheses(cells, "turbulence", "maddpg", 500)
    assert found["H2"]["p"] > 0.95 and found["H2"]["holds"] is False
    # The same effect today: no larger in the column, H3's interval straddles 0.
    cells[("today", "turbulence", "maddpg", "plain")] = made_up(list(0.2 + SPREAD))
    cells[("today", "turbulence", "maddpg", "ccr")] = made_up(list(0.3 + SPREAD))
    found = analysis.hypotheses(cells, "turbulence", "maddpg", 500)
    assert found["H3"]["ci_low"] < 0 < found["H3"]["ci_high"] and found["H3"]["holds"] is False


def test_a_cells_row_and_the_regimes_aggregates():
    row = analysis.cell_row(made_up(list(0.3 + SPREAD)))
    assert row["forewarned_share"]["n"] == 4  # the seed without danger left out
    assert row["forewarned_share"]["mean"] == pytest.approx(0.45)
    assert row["danger_frequency"]["mean"] == pytest.approx(0.3)
    cells = {("column", s, "maddpg", v): made_up(list(level + SPREAD))
             for s in ("turbulence", "hidden_obstacle")
             for v, level in (("plain", 0.3), ("ccr", 0.1))}
    cells[("column", "turbulence", "maddpg", "ccr_scores")] = made_up(list(0.3 + SPREAD))
    found = analysis.aggregates(cells, "column", resamples=200)
    assert found["pairs"] == ["hidden_obstacle-maddpg", "turbulence-maddpg"]
    assert set(found["iqm"]["danger_frequency"]) == {"plain", "ccr"}  # made in every pair
    assert found["iqm"]["danger_frequency"]["ccr"]["iqm"] == pytest.approx(0.1, abs=0.01)
    assert found["ccr_safer_than_plain"]["probability"] == pytest.approx(1.0)


def study_record(regime: str, variant: str, seeds: int = 5, value: float = 3.0) -> dict:
    """The settings record of a study cell of ``variant`` as study.py writes it, every
    searched value ``value``."""
    program = next(p for p in study.PROGRAMS if variant in p)
    settings = study.Settings(values={v: value for v in program if v in study.SEARCHED},
                              regime=regime, seeds=tuple(range(seeds)),
                              eval_every=protocol.REGIMES[regime].eval_every)
    return settings_record(settings.for_program(program))


def test_the_report_states_each_variants_effect_and_the_hypotheses(tmp_path, capsys,
                                                                     monkeypatch):
    """Made-up cells of both regimes written as study.py writes them: the effects are
    signed so that better is positive, the report gives every hypothesis its verdict on the
    study's seeds 0-4 (a cell of ten seeds is cut to them), leaves out and names a cell
    made with another value than its search chose, and a folder without a study is one
    line."""
    monkeypatch.setattr(study, "chosen", lambda *args: {"value": 3.0, "fallback": False})
    for regime, ccr in (("today", 0.30), ("column", 0.20)):
        folder = tmp_path / regime
        (folder / "cells").mkdir(parents=True)
        (folder / "study_cells.json").write_text("{}")
        for variant, level in (("plain", 0.30), ("ccr", ccr), ("danger_flags", 0.25),
                               ("ccr_reward", 0.1)):
            seeds = 10 if (regime, variant) == ("column", "ccr") else 5
            danger = list(level + SPREAD)
            if seeds == 10:  # seeds 5-9 far below: the primary analysis must not see them
                danger += [0.0] * 5
            cell = {**made_up(danger), "scenario": "turbulence", "algo": "maddpg",
                    "variant": variant, "seeds": list(range(seeds)), "budget": 3_000_000,
                    "settings": study_record(regime, variant, seeds,
                                             1.0 if variant == "ccr_reward" else 3.0)}
            cell["measures"]["forewarned_share"] = [0.5] * seeds
            (folder / "cells" / f"turbulence-maddpg-{variant}.json").write_text(
                json.dumps(cell))
    cells = {**report.read_cells(tmp_path / "today", "today"),
             **report.read_cells(tmp_path / "column", "column")}
    assert len(cells) == 8
    primary, whole, values, left_out = report.protocol_cells(
        cells, {"today": tmp_path / "s", "column": tmp_path / "s"})
    assert len(primary) == 6 and len(left_out) == 2  # ccr_reward made at lambda 1, not 3
    assert all("ccr_reward: made with other values" in line for line in left_out)
    assert len(primary[("column", "turbulence", "maddpg", "ccr")]["seeds"]) == 5
    assert len(whole[("column", "turbulence", "maddpg", "ccr")]["seeds"]) == 10
    assert values["column"]["ccr"].startswith("3 (the search in")
    found = report.effect(primary, "column", "turbulence", "maddpg", "ccr", "danger_frequency")
    assert found["effect"] == pytest.approx(0.10) and found["ci_low"] > 0
    assert report.effect(primary, "column", "turbulence", "maddpg", "ccr_reward",
                         "danger_frequency") is None
    assert report.main(["--out", str(tmp_path)]) == 0
    text = (tmp_path / "study.md").read_text()
    assert "* H1 (today: CCR's danger is plain's): **holds**, CCR's danger +0.0%" in text
    assert "* H2 (column: CCR's danger below plain's, success within 5 points): **holds**" in text
    assert "* H3 (CCR's effect larger in the column): **holds**, +10.0%" in text
    assert "H4 column/danger_flags, danger against plain: -5.0%" in text
    assert "* `column` (turbulence-maddpg): interquartile mean of danger plain 30.0%" in text
    assert "; of success plain 90.0%" in text
    assert "P(a CCR run is safer than a plain one) 1.00" in text
    assert "* column: turbulence-maddpg-ccr_reward: made with other values" in text
    assert "Values: " in text and "Budget: 3,000,000 steps per run" in text
    assert "## Hypotheses on every seed made" in text and "waits until every cell" in text
    assert (tmp_path / "effects.png").stat().st_size > 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        report.main(["--out", str(tmp_path / "empty")])
    assert exit_.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line]
    assert len(err) == 1 and "no study cells" in err[0]
