"""The numbers the tables compute (``experiments/tables_statistics.py``) from finished
cells, on made-up cells (no training): the paper's headline formula, the claim scorecard,
rliable's aggregates and the training-danger share.
The whole grid's pipeline is ``tests/test_tables.py`` (slow)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from ccrjax.run.stats import plateau_or_undetermined

SCRIPT = Path(__file__).resolve().parent.parent / "experiments" / "tables.py"


@pytest.fixture(scope="module")
def tables():
    """The statistics module, which holds the grid's names it computes over."""
    return importlib.import_module("experiments.tables_statistics")


@pytest.fixture(scope="module")
def report():
    return importlib.import_module("experiments.tables_report")


def made_up_cells(tables, danger, success, algos=None) -> dict:
    """Cells of every scenario x learner (``algos``, default the paper's three) x variant;
    ``danger(scenario, algo, variant)`` and ``success(...)`` give each cell's per-seed
    values."""
    return {(s, a, v): {"final": {"danger_frequency": list(danger(s, a, v)),
                                  "success_rate": list(success(s, a, v))}}
            for s in tables.PAPER_SCENARIOS for a in (algos or tables.ALGOS)
            for v in tables.VARIANTS}


def test_the_paper_headlines_follow_from_its_tables(tables):
    """Our headline formula, applied to the paper's own tables, gives the paper's figures."""
    cells = {}
    for (scenario, algo, variant), danger in tables.PAPER["danger_frequency"].items():
        success = tables.PAPER["success_rate"][(scenario, algo, variant)]
        cells[(scenario, algo, variant)] = {"final": {"danger_frequency": [danger],
                                                      "success_rate": [success]}}
    assert set(tables.HEADLINES) == set(tables.PAPER_HEADLINES) - {
        "training_danger_share_maddpg_hidden_obstacle"}  # that one needs training counts
    for key, definition in tables.HEADLINES.items():
        result = tables.headline(cells, *definition, resamples=2000)
        assert result["mean"] == pytest.approx(tables.PAPER_HEADLINES[key], abs=6e-4), key
        # One value per cell: every resample is the data itself, so the interval is a point.
        assert result["ci_low"] == pytest.approx(result["mean"], rel=1e-12)
        assert result["ci_high"] == pytest.approx(result["mean"], rel=1e-12)
        assert len(result["per_pair"]) == len(result["pair_names"]) == 3 * len(definition[4])
        assert np.mean(result["per_pair"]) == pytest.approx(result["mean"], rel=1e-12)
    # Turbulence's success with CCR, pair by pair (Table II: DDPG 97.48% -> 70.34%).
    turbulence = tables.headline(cells, *tables.HEADLINES["success_change_vs_plain_turbulence"])
    assert turbulence["pair_names"][0] == "turbulence, IDDPG"
    assert turbulence["per_pair"][0] == pytest.approx(70.34 / 97.48 - 1.0, rel=1e-9)


def test_the_obstacle_distance_ratio_is_ccr_over_plain_by_arrival_rank(tables):
    """Per rank: the mean over seeds of CCR's distance over the same for plain."""
    cells = {("hidden_obstacle", "maddpg", "plain"): {"arrival": {"centre_distance": [
                 [0.5, 1.0, 2.0], [0.7, 1.0, 2.0]]}},
             ("hidden_obstacle", "maddpg", "ccr"): {"arrival": {"centre_distance": [
                 [0.6, 3.0, 2.0], [0.84, 3.0, 2.0]]}}}
    ratio = tables.obstacle_distance_ratio(cells)
    assert ratio["by_rank"] == pytest.approx([1.2, 3.0, 1.0])
    assert (ratio["low"], ratio["high"]) == pytest.approx((1.0, 3.0))
    assert ratio["paper"] == [1.2, 4.7]


def test_the_scorecard_counts_lower_significant_and_holm_cells(tables):
    """CCR below plain in 4 cells, clearly (p << 0.05/9) in 2 of them; never below the
    pessimistic baseline; on the hidden obstacle above both in success with MADDPG only."""
    clear = {("turbulence", "iddpg"), ("strong_wind", "maddpg")}
    slight = {("turbulence", "maac"), ("hidden_obstacle", "iddpg")}

    def danger(s, a, v):
        if v == "pessimistic":
            return [0.01, 0.02, 0.015]
        if v == "plain":
            return [0.30, 0.31, 0.32] if (s, a) in clear else [0.21, 0.19, 0.23]
        if (s, a) in clear:
            return [0.10, 0.11, 0.12]
        return [0.10, 0.30, 0.20] if (s, a) in slight else [0.25, 0.26, 0.27]

    def success(s, a, v):
        if s == "hidden_obstacle" and a == "maddpg":
            return [0.95, 0.96, 0.97] if v == "ccr" else [0.50, 0.52, 0.54]
        return [0.8, 0.8, 0.8]

    cells = made_up_cells(tables, danger, success)
    card = tables.claims(cells, tables.welch_marks(cells))
    plain = card["danger_lower_vs_plain"]
    assert (plain["cells"], plain["significant"], plain["significant_holm"], plain["of"]) == (
        4, 2, 2, 9)
    assert {(d["scenario"], d["algo"]) for d in plain["detail"] if d["lower"]} == clear | slight
    pessimistic = card["danger_lower_vs_pessimistic"]
    assert (pessimistic["cells"], pessimistic["significant"]) == (0, 0)
    raised = card["hidden_obstacle_success_above_both"]
    assert (raised["learners"], raised["significant"], raised["of"]) == (1, 1, 3)
    assert [r["algo"] for r in raised["detail"] if r["above_both"]] == ["maddpg"]


def test_rliable_aggregates_on_made_up_cells(tables):
    """Every CCR run below every plain run in danger: probability of improvement 1 (lower
    is better for danger); equal to the pessimistic runs: 1/2; IQMs are the constant scores."""
    levels = {"plain": 0.3, "pessimistic": 0.1, "ccr": 0.1}
    cells = made_up_cells(tables, lambda s, a, v: [levels[v]] * 5, lambda s, a, v: [0.9] * 5)
    result = tables.aggregates(cells, resamples=200)
    danger = result["danger_frequency"]
    for variant, level in levels.items():
        assert danger["iqm"][variant]["iqm"] == pytest.approx(level)
    improvement = danger["probability_of_improvement"]
    assert improvement["plain"]["probability"] == pytest.approx(1.0)
    assert improvement["pessimistic"]["probability"] == pytest.approx(0.5)
    assert result["success_rate"]["probability_of_improvement"]["plain"]["probability"] == (
        pytest.approx(0.5))


def test_the_training_danger_share_is_ccrs_over_plains(tables):
    """The paper's 28.09%: MADDPG+CCR's dangerous training steps over plain MADDPG's, on the
    hidden obstacle; other cells do not enter it."""
    cells = {}
    for (s, a, v) in [(s, a, v) for s in tables.PAPER_SCENARIOS for a in tables.ALGOS
                      for v in tables.VARIANTS]:
        steps = {"plain": [1000.0, 1000.0], "pessimistic": [600.0, 700.0],
                 "ccr": [250.0, 300.0]}[v]
        if (s, a) != ("hidden_obstacle", "maddpg"):
            steps = [7.0, 9.0]
        cells[(s, a, v)] = {"final": {"learning_danger_steps": steps}}
    share = tables.training_danger_share(cells)
    assert share["mean"] == pytest.approx(0.275)
    assert share["ci_low"] <= share["mean"] <= share["ci_high"]
    assert 0.25 - 1e-9 <= share["ci_low"] and share["ci_high"] <= 0.30 + 1e-9
    assert np.isfinite([share["ci_low"], share["ci_high"]]).all()


def test_the_plateau_table_shows_how_far_each_plain_curve_moved(report):
    """A curve that fails the test shows its rise beside the interval it left; one too
    short to judge says why instead of a number."""
    rising = np.arange(10.0)[None, :] + 0.1 * np.arange(5.0)[:, None]  # 5 seeds, close
    flat = np.array([[-10.0] * 10, [-10.5] * 10])
    records = [
        {"scenario": "turbulence", "algo": "iddpg",
         "return_plateau": plateau_or_undetermined(rising)},
        {"scenario": "strong_wind", "algo": "maac",
         "return_plateau": plateau_or_undetermined(flat)},
        {"scenario": "hidden_obstacle", "algo": "maddpg",
         "return_plateau": plateau_or_undetermined(flat[:1])},
    ]
    lines = report.plateau_table(records)
    assert len(lines) == 2 + 3 + 1  # header, rows, blank
    # Last two points 8.0 and 9.0 (+0.2 on average over seeds), the two before 6 and 7.
    assert lines[2].startswith("| turbulence, IDDPG | 8.70 | 6.70 [")
    assert "| +2.00 (+29.9%) | **no** |" in lines[2]
    assert lines[3].endswith("| +0.00 (+0.0%) | yes |")
    assert "undetermined: plateau needs curves [seeds >= 2" in lines[4]
    # A return of exactly 0 before gives the change without a percentage, not an error.
    zero = report.plateau_table([{"scenario": "turbulence", "algo": "maac",
                                  "return_plateau": plateau_or_undetermined(flat * 0)}])
    assert zero[2].endswith("| +0.00 | yes |")


def test_the_on_policy_familys_numbers_run_over_its_own_six_pairs(tables):
    """IPPO and MAPPO (docs/protocol.md, amendment of 2026-12-02): the scorecard, the
    aggregates and the headline averages over their 6 pairs, the paper's learners absent."""
    family = ("ippo", "mappo")

    def danger(s, a, v):
        if v == "ccr" and a == "mappo":
            return [0.05, 0.06, 0.05]
        return [0.20, 0.21, 0.19]

    cells = made_up_cells(tables, danger, lambda s, a, v: [0.9, 0.9, 0.9], family)
    card = tables.claims(cells, tables.welch_marks(cells, family), family)
    plain = card["danger_lower_vs_plain"]
    assert (plain["cells"], plain["significant"], plain["of"]) == (3, 3, 6)
    assert {d["algo"] for d in plain["detail"] if d["lower"]} == {"mappo"}
    assert card["hidden_obstacle_success_above_both"]["of"] == 2
    result = tables.aggregates(cells, resamples=200, algos=family)
    assert result["danger_frequency"]["probability_of_improvement"]["plain"][
        "probability"] == pytest.approx(0.5 + 0.5 * 3 / 6)  # half the pairs all better
    change = tables.headline(cells, *tables.HEADLINES["danger_reduction_vs_plain"],
                             algos=family)
    assert change["pair_names"] == [f"{name}, {learner}" for name in
                                    ("hidden obstacle", "turbulence", "strong wind")
                                    for learner in ("IPPO", "MAPPO")]
    assert change["mean"] == pytest.approx(np.mean([0.0, 1 - 0.16 / 0.6] * 3), rel=1e-9)


def test_variants_choose_the_programs_and_pessimistic_alone_is_its_own():
    """``tables.py --variants``: plain always trains beside pessimistic (one program);
    pessimistic without plain is a program of its own; the default is the whole grid."""
    from experiments.tables_grid import Settings, jobs_of

    settings = Settings(lam=3.0, penalty=1.0, scenarios=("turbulence",), algos=("iddpg",))
    names = lambda variants: [job.name for job in jobs_of(settings, variants)]  # noqa: E731
    assert names(("plain", "pessimistic", "ccr")) == [
        "turbulence-iddpg-plain+pessimistic", "turbulence-iddpg-ccr"]
    assert [job.name for job in jobs_of(settings)] == names(("plain", "pessimistic", "ccr"))
    assert names(("pessimistic",)) == ["turbulence-iddpg-pessimistic"]
    assert names(("plain",)) == ["turbulence-iddpg-plain+pessimistic"]
    assert names(("ccr",)) == ["turbulence-iddpg-ccr"]
    assert names(("pessimistic", "ccr")) == ["turbulence-iddpg-pessimistic",
                                              "turbulence-iddpg-ccr"]
    assert settings.run_params("pessimistic") == {"penalty": 1.0}
