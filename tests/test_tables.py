"""``experiments/tables.py --quick``: the whole grid, its files, and resuming by cells.

The quick mode trains all 18 programs (3 scenarios x 3 learners x {plain and pessimistic,
CCR}) with tiny networks for a few hundred steps: it checks the pipeline (cells, tables,
headline figures, figures, resuming), not the learning.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

# The whole grid's pipeline (18 programs compiled): minutes, so `make test-slow`.
pytestmark = pytest.mark.slow

SCRIPT = Path(__file__).resolve().parent.parent / "experiments" / "tables.py"


def load_module(name: str):
    return importlib.import_module(f"experiments.{name}")


@pytest.fixture(scope="module")
def tables():
    return load_module("tables")


@pytest.fixture(scope="module")
def quick_run(tables, tmp_path_factory):
    out = tmp_path_factory.mktemp("tables")
    assert tables.main(["--quick", "--out", str(out)]) == 0
    return out


def assert_cells_record_their_training(out: Path) -> None:
    """Every cell written holds the record of what it was trained with, equal to what the
    current code expects for it (``cell_identity.cell_is_current``)."""
    from experiments import cell_identity

    cells = sorted((out / "cells").glob("*.json"))
    assert cells
    for path in cells:
        cell = json.loads(path.read_text())
        expected = cell_identity.expected_training(cell, cell["settings"])
        assert cell["training"] == expected, path.name


def test_quick_mode_writes_the_tables_the_json_and_the_figures(tables, quick_run):
    statistics = load_module("tables_statistics")
    grid = (statistics.PAPER_SCENARIOS, statistics.ALGOS, statistics.VARIANTS)
    out = quick_run
    assert_cells_record_their_training(out)
    text = (out / "tables.md").read_text()
    for heading in ("Table I: dangerous-behaviour frequency", "Table II: success rate",
                    "headline figures", "Scorecard", "Aggregates over the 9",
                    "Did the plain learners converge?", "Dangerous robot-steps during training",
                    "Did training stay finite?"):
        assert heading in text
    assert "Every update of the 54 runs stayed finite." in text  # 27 cells x 2 seeds
    assert "MADDPG+CCR" in text and "(40.92%)" in text  # the paper's number beside ours
    assert "go-to-goal (reference)" in text and "oracle (reference)" in text
    result = json.loads((out / "tables.json").read_text())
    records = result["records"]
    assert len(records) == 27
    assert {(r["scenario"], r["algo"], r["variant"]) for r in records} == {
        (s, a, v) for s in grid[0] for a in grid[1] for v in grid[2]}
    for record in records:
        danger = record["danger_frequency"]
        assert len(danger["per_seed"]) == 2
        assert danger["mean"] == pytest.approx(sum(danger["per_seed"]) / 2)
        assert "paper" in danger and "paper" in record["success_rate"]
        # Intervals within the metric's range; every cell knows where and how it was made.
        for metric in ("danger_frequency", "success_rate"):
            if record[metric]["ci_low"] is not None:
                assert 0.0 <= record[metric]["ci_low"] <= record[metric]["ci_high"] <= 1.0
        assert "plateaued" in record["return_plateau"]
        assert record["nonfinite_iteration"] == [-1, -1]
        assert record["device"] == load_module("ledger").device_name()
        assert record["program_seconds"] > 0
        if record["variant"] == "ccr":
            assert set(record["danger_frequency"]["welch"]) == {"plain", "pessimistic"}
    assert set(result["headlines"]) == set(statistics.PAPER_HEADLINES)
    assert "Each pair's relative change" in text and "(turbulence)" in text
    assert text.count("**Quick mode**") == 1
    ratio = result["obstacle_distance_ratio_maddpg"]
    assert len(ratio["by_rank"]) >= 2 and ratio["low"] <= ratio["high"]  # one per robot
    assert f"{ratio['low']:.2f}x to {ratio['high']:.2f}x" in text
    for metric in ("danger_frequency", "success_rate"):
        aggregate = result["aggregates"][metric]
        assert set(aggregate["iqm"]) == set(statistics.VARIANTS)
        for value in aggregate["probability_of_improvement"].values():
            assert 0.0 <= value["ci_low"] <= value["probability"] <= value["ci_high"] <= 1.0
    assert len(result["controllers"]) == 6
    assert result["sources"]["lam"] == "the quick mode's fixed value"
    # The claims follow from the records: CCR's mean danger below the other variant's,
    # counted cell by cell.
    by_key = {(r["scenario"], r["algo"], r["variant"]): r for r in records}
    for base in ("plain", "pessimistic"):
        claim = result["claims"][f"danger_lower_vs_{base}"]
        lower = [
            by_key[(s, a, "ccr")]["danger_frequency"]["mean"]
            < by_key[(s, a, base)]["danger_frequency"]["mean"]
            for s in statistics.PAPER_SCENARIOS for a in statistics.ALGOS
        ]
        assert claim["of"] == len(lower) == 9
        assert claim["cells"] == sum(lower)
        assert [d["lower"] for d in claim["detail"]] == lower
        assert 0 <= claim["significant_holm"] <= claim["significant"] <= claim["cells"]
    for figure in ("trajectories_hidden_obstacle_maddpg.png",
                   "distance_hidden_obstacle_maddpg.png", "progress_hidden_obstacle.png",
                   "progress_turbulence.png", "progress_strong_wind.png",
                   *(f"curves_{s}_{a}.png" for s in grid[0] for a in grid[1])):
        assert (out / figure).stat().st_size > 0
    cells = sorted((out / "cells").iterdir())
    assert len(cells) == 27 and not [c for c in cells if c.name.startswith(".")]


def test_a_rerun_skips_finished_cells_and_redoes_missing_ones(tables, quick_run, capsys):
    out = quick_run
    missing = out / "cells" / "strong_wind-maac-ccr.json"
    missing.unlink()
    kept = out / "cells" / "turbulence-iddpg-plain.json"
    before = kept.read_text()
    capsys.readouterr()
    # --no-train summarises or says, in one line before anything compiles, what is missing
    # or was made otherwise (here every cell, under another lambda).
    for argv, fragments in (
            ([], ("--no-train: 1 of the 27 cells in", "strong_wind-maac-ccr: none made",
                  "run without --no-train to train them")),
            (["--lam", "2"], ("--no-train: 27 of the 27 cells",
                              "hidden_obstacle-iddpg-plain: made with other lam;",
                              "; and 23 more"))):
        with pytest.raises(SystemExit) as exit_:
            tables.main(["--quick", "--no-train", *argv, "--out", str(out)])
        assert exit_.value.code == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and all(f in lines[0] for f in fragments), lines
    assert tables.main(["--quick", "--out", str(out)]) == 0
    log = capsys.readouterr().err
    assert "17 of 18 programs already done; 1 to train" in log
    assert missing.exists()
    assert kept.read_text() == before
    runs = json.loads((out / "tables.json").read_text())["invocations"]
    assert [(r["programs_trained"], r["finished"]) for r in runs] == [(18, True), (1, True)]
    assert tables.main(["--quick", "--no-train", "--out", str(out)]) == 0
    assert "18 of 18 programs already done; 0 to train" in capsys.readouterr().err


def test_a_killed_run_keeps_its_record_and_the_programs_it_finished(
        tables, quick_run, kill_grid_in_program, capsys):
    out = quick_run
    for name in ("strong_wind-maddpg-ccr.json", "strong_wind-maac-ccr.json"):
        (out / "cells" / name).unlink()
    kill_grid_in_program(2)  # killed during the second program
    argv = ["--quick", "--out", str(out), "--checkpoint-minutes", "0.000001"]  # every chunk
    with pytest.raises(KeyboardInterrupt):
        tables.main(argv)
    ledger = json.loads((out / "invocations.json").read_text())["invocations"]
    assert (ledger[-1]["programs_trained"], ledger[-1]["finished"]) == (1, False)
    assert (out / "cells" / "strong_wind-maddpg-ccr.json").exists()
    assert not (out / "cells" / "strong_wind-maac-ccr.json").exists()
    # The first program's checkpoint went with its cell; the killed one's is kept.
    assert [p.name for p in (out / "partial").iterdir()] == ["strong_wind-maac-ccr"]

    kill_grid_in_program(None)
    capsys.readouterr()
    assert tables.main(argv) == 0
    err = capsys.readouterr().err
    assert "17 of 18 programs already done; 1 to train" in err
    assert "resuming from its checkpoint after 1 of 2 evaluations" in err
    assert not (out / "partial").exists()
    runs = json.loads((out / "tables.json").read_text())["invocations"]
    assert [(r["programs_trained"], r["finished"]) for r in runs][-2:] == [(1, False), (1, True)]
    assert "stopped before the end" in (out / "tables.md").read_text()


def test_the_searches_pipeline_at_a_tiny_size(tmp_path, capsys, monkeypatch):
    """Both searches over one scenario and learner: the cells, the choice by the rule,
    the files; then a re-run that trains nothing."""
    search = load_module("search")
    out = tmp_path / "search"
    argv = ["--variant", "pessimistic", "--quick", "--scenarios", "turbulence", "--algos",
            "iddpg", "--values", "0.1", "1", "--out", str(out)]
    titles = []
    draw = search.draw_search_tradeoff

    def recording(panels, *args, **kwargs):
        titles.extend(panels)
        return draw(panels, *args, **kwargs)

    monkeypatch.setattr(search, "draw_search_tradeoff", recording)
    assert search.main(argv) == 0
    monkeypatch.setattr(search, "draw_search_tradeoff", draw)
    # A quick figure copied out alone still says what it is.
    assert len(titles) == 2 and all(t.startswith(search.protocol.QUICK_FIGURE) for t in titles)
    result = json.loads((out / "search.json").read_text())
    assert result["parameter"] == "penalty"
    assert [row["value"] for row in result["aggregate"]] == [0.0, 0.1, 1.0]
    assert result["selection"]["value"] in (0.1, 1.0)
    assert not result["selection"]["protocol"]  # one pair, quick: provisional
    assert "the quick mode" in result["selection"]["provisional_because"]
    # tradeoff.png marks the rule's threshold, 5 points of success below the reference's.
    mark = search.choice_mark(result["selection"])
    assert mark.threshold == pytest.approx(result["selection"]["reference_constraint"] - 0.05)
    assert (mark.value, mark.label) == (result["selection"]["value"], "provisional choice")
    assert result["pairs"][0]["device"] == search.device_name()  # e.g. "cpu:cpu x1"
    assert_cells_record_their_training(out)
    for name in ("search.md", "tradeoff.png", "tradeoff_pairs.png", "invocations.json"):
        assert (out / name).stat().st_size > 0
    assert "**Quick mode**" in (out / "search.md").read_text()
    runs = len(json.loads((out / "cells" / "turbulence-iddpg.json").read_text())["grid_seeds"])
    assert result["runs"] == runs and result["nonfinite"] == []
    assert f"Every update of the {runs} runs stayed finite." in (out / "search.md").read_text()
    capsys.readouterr()
    assert search.main(argv) == 0
    assert "1 of 1 programs already done; 0 to train" in capsys.readouterr().err
    wider = [*argv[:4], "turbulence", "strong_wind", *argv[5:]]  # the cell made above is kept
    assert search.main(wider) == 0
    assert "1 of 2 programs already done; 1 to train" in capsys.readouterr().err
    runs = json.loads((out / "invocations.json").read_text())["invocations"]
    assert [r["programs_trained"] for r in runs] == [1, 0, 1]  # the narrower ones' kept too


def test_the_budgets_pipeline_at_a_tiny_size(tmp_path, capsys):
    """The plain learners' budget check over one scenario and two learners: the cells, the
    checks and the proposal, the files; then a re-run that trains nothing and a wider one
    that trains only the new cell."""
    budgets = load_module("budgets")
    out = tmp_path / "budgets"
    argv = ["--quick", "--scenarios", "turbulence", "--algos", "iddpg", "--out", str(out)]
    assert budgets.main(argv) == 0
    result = json.loads((out / "budgets.json").read_text())
    (cell,) = result["cells"]
    assert (cell["scenario"], cell["algo"], cell["seeds"]) == ("turbulence", "iddpg",
                                                              [200, 201, 202])
    assert all(len(curve) == len(cell["env_steps"]) for curve in cell["curves"]["return"])
    assert cell["checks"][-1]["budget"] == cell["env_steps"][-1]
    assert cell["plateaued_at_budget"] == cell["checks"][-1]["plateaued"]
    assert cell["device"] == budgets.device_name()
    assert cell["nonfinite_iteration"] == [-1, -1, -1]
    assert "Every update of the 3 runs stayed finite." in (out / "budgets.md").read_text()
    assert_cells_record_their_training(out)
    for name in ("budgets.md", "curves_iddpg.png", "invocations.json"):
        assert (out / name).stat().st_size > 0
    capsys.readouterr()
    assert budgets.main(argv) == 0
    assert "1 of 1 programs already done; 0 to train" in capsys.readouterr().err
    wider = [*argv[:4], "iddpg", "maddpg", *argv[5:]]
    assert budgets.main(wider) == 0
    assert "1 of 2 programs already done; 1 to train" in capsys.readouterr().err
    assert (out / "curves_maddpg.png").exists()
    runs = json.loads((out / "invocations.json").read_text())["invocations"]
    assert [r["programs_trained"] for r in runs] == [1, 0, 1]
    assert budgets.main(argv) == 0  # a narrower invocation still reports every cell
    cells = json.loads((out / "budgets.json").read_text())["cells"]
    assert [(c["scenario"], c["algo"]) for c in cells] == [("turbulence", "iddpg"),
                                                            ("turbulence", "maddpg")]
    other = [*wider, "--candidate-every", "1000"]  # other checks of the same curves
    assert budgets.main(other) == 0
    assert "2 of 2 programs already done; 0 to train" in capsys.readouterr().err
    cell = json.loads((out / "budgets.json").read_text())["cells"][0]
    assert [c["budget"] for c in cell["checks"]] == [1000, 2000, 3000, 4000]
    longer = [*wider, "--steps", "4200"]  # other cells: refused, then trained over with --force
    with pytest.raises(SystemExit) as refusal:
        budgets.main(longer)
    assert refusal.value.code == 2
    assert "cells made with other settings (budget" in capsys.readouterr().err
    assert budgets.main([*longer, "--force"]) == 0
    runs = json.loads((out / "invocations.json").read_text())["invocations"]
    assert [r["programs_trained"] for r in runs] == [2]


def test_a_narrower_invocation_trains_its_programs_and_waits_for_the_rest(tables, tmp_path,
                                                                          capsys):
    """--scenarios and --algos split the grid (lanes side by side on a GPU): the named
    programs are trained, and the tables are written only when all 18 exist."""
    out = tmp_path / "lane"
    argv = ["--quick", "--scenarios", "turbulence", "--algos", "iddpg", "--out", str(out)]
    assert tables.main(argv) == 0
    printed = capsys.readouterr().out
    assert "2 of the 2 programs this command names made" in printed
    assert "the whole grid's 18 exist" in printed and "strong_wind-maac-ccr" in printed
    assert sorted(p.name for p in (out / "cells").iterdir()) == [
        f"turbulence-iddpg-{v}.json" for v in ("ccr", "pessimistic", "plain")]
    assert not (out / "tables.md").exists()




def test_pessimistic_alone_trains_the_runs_it_trains_beside_plain(tables, quick_run, tmp_path,
                                                                  capsys):
    """``--variants pessimistic`` trains a program of the pessimistic runs alone (the cells
    of another penalty, without plain's again): the same configurations and seeds as the
    pessimistic half of the program beside plain, so the same final numbers. Its end says
    the program it names is made, and that the tables wait for the whole grid."""
    out = tmp_path / "alone"
    argv = ["--quick", "--scenarios", "turbulence", "--algos", "iddpg", "--variants",
            "pessimistic", "--out", str(out)]
    assert tables.main(argv) == 0
    assert "1 of the 1 programs this command names made" in capsys.readouterr().out
    assert sorted(p.name for p in (out / "cells").iterdir()) == [
        "turbulence-iddpg-pessimistic.json"]
    alone = json.loads((out / "cells" / "turbulence-iddpg-pessimistic.json").read_text())
    beside = json.loads((quick_run / "cells" / "turbulence-iddpg-pessimistic.json").read_text())
    assert alone["params"] == beside["params"] and alone["seeds"] == beside["seeds"]
    for metric, values in beside["final"].items():
        assert alone["final"][metric] == pytest.approx(values, abs=1e-5), metric
