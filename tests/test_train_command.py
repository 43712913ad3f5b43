"""``python -m ccrjax.train`` and ``python -m ccrjax.evaluate``: the run folder, checkpoints that
resume exactly (after SIGKILL and Ctrl-C of a real subprocess), and every kind of bad input.

All runs use one tiny configuration (2 seeds, 2 environments of 10 steps, 16-unit
networks), so the program compiles once; the session's compilation cache
(``conftest.py``) serves the subprocesses and later runs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ccrjax
from ccrjax import evaluate, terminal, train
from ccrjax.run import session as sessions
from ccrjax.run.checkpoint import Checkpoints
from ccrjax.run.folder import (
    CSV_COLUMNS,
    RunFolder,
    fingerprint,
    read_metrics,
    tree_code_commit,
    tree_commit,
)
from ccrjax.training import make_train

TINY = [
    "--scenario", "hidden_obstacle", "--algo", "maddpg", "--variant", "pessimistic",
    "--steps", "3000", "--num-envs", "2", "--episode-length", "10", "--eval-every", "200",
    "--eval-episodes", "4", "--learning-starts", "100", "--ddpg-batch-size", "32",
    "--ddpg-actor-hidden", "16", "--ddpg-critic-hidden", "16", "--ddpg-update-every", "10",
    "--seeds", "2", "--seed-offset", "3", "--checkpoint-every", "200", "--keep-checkpoints", "3",
    "--no-progress", "--keep-buffer",
]
FINAL_STEPS = 3000


def run_main(module, argv, capsys):
    """``module.main(argv)``'s exit status and what it printed."""
    try:
        status = module.main([str(a) for a in argv])
    except SystemExit as exit_:
        status = exit_.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def assert_usage_error(status, err, *fragments):
    assert status == 2, err
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def final_state(folder: Path):
    """The latest checkpoint of a run folder, restored."""
    spec = train.RunSpec.from_dict(RunFolder(folder).read_config()["run"])
    program = make_train(spec.train)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in spec.seed_list])
    abstract = jax.eval_shape(jax.vmap(program.init), keys)
    checkpoints = Checkpoints(folder / "checkpoints")
    try:
        return checkpoints.restore_latest(abstract.replace(buffer=None), abstract.buffer,
                                              fingerprint(spec.to_dict()))
    finally:
        checkpoints.close()


def assert_same_run(a: Path, b: Path):
    """Same parameters, buffers, keys and counters, and the same metrics (wall time aside)."""
    restored_a, restored_b = final_state(a), final_state(b)
    assert restored_a.step == restored_b.step == FINAL_STEPS
    assert restored_a.buffer is not None and restored_b.buffer is not None  # --keep-buffer
    leaves_a = jax.tree_util.tree_leaves((restored_a.state, restored_a.buffer))
    leaves_b = jax.tree_util.tree_leaves((restored_b.state, restored_b.buffer))
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    rows_a, rows_b = read_metrics(a / "metrics.csv"), read_metrics(b / "metrics.csv")
    assert len(rows_a) == len(rows_b) == 2 * (FINAL_STEPS // 200 + 1)
    for row_a, row_b in zip(rows_a, rows_b, strict=True):
        for column in CSV_COLUMNS:
            if column != "wall_time_s":
                assert row_a[column] == row_b[column], (column, row_a, row_b)
    summary_a = json.loads((a / "summary.json").read_text())
    summary_b = json.loads((b / "summary.json").read_text())
    assert summary_a["per_seed"] == summary_b["per_seed"]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """The tiny run, never interrupted (in this process)."""
    out = tmp_path_factory.mktemp("runs") / "uninterrupted"
    status = train.main([*TINY, "--out", str(out)])
    assert status == 0
    return out


def start_subprocess(out: Path, env, *extra):
    return subprocess.Popen(
        [sys.executable, "-m", "ccrjax.train", *TINY, "--out", str(out), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )


def wait_for(path: Path, process: subprocess.Popen, timeout: float = 240.0):
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.005)


# ---------------------------------------------------------------------------- the folder
def test_help_lists_every_option_with_its_default():
    text = train.build_parser().format_help()
    for option in ("--scenario", "--algo", "--variant", "--lam", "--seeds", "--seed-offset",
                   "--steps", "--num-envs", "--robots", "--out", "--resume",
                   "--checkpoint-every", "--keep-checkpoints", "--ddpg-actor-lr",
                   "--ddpg-batch-size", "--maac-policy-lr", "--maac-gradient-steps"):
        assert option in text
    parser = train.build_parser()
    for action in parser._actions:
        if action.option_strings and action.help not in (None, "==SUPPRESS==") and (
            action.dest not in ("help", "resume", "no_progress", "no_compilation_cache")
        ):
            assert "default" in action.help, action.option_strings


def test_a_finished_run_leaves_everything_in_its_folder(finished_run):
    out = finished_run
    for name in ("config.json", "metrics.csv", "summary.json", "curves.png", "episode.png",
                 "episode.gif"):
        assert (out / name).stat().st_size > 0, name
    config = json.loads((out / "config.json").read_text())
    for key in ("ccrjax_version", "git_commit", "jax_version", "devices", "run"):
        assert key in config
    assert config["run"]["train"]["transform"]["penalty"] == 1.0
    assert config["run"]["train"]["learner"]["critic_hidden"] == [16]
    rows = read_metrics(out / "metrics.csv")
    assert {r["seed"] for r in rows} == {3, 4}
    assert sorted({r["env_steps"] for r in rows}) == list(range(0, FINAL_STEPS + 1, 200))
    danger = [r["cumulative_danger_steps"] for r in rows if r["seed"] == 3]
    assert danger == sorted(danger) and danger[-1] > 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["per_seed"]) == {"3", "4"}
    stats = summary["mean_ci95"]["return"]
    values = [summary["per_seed"][s]["return"] for s in ("3", "4")]
    assert stats["mean"] == pytest.approx(np.mean(values))
    assert stats["ci_low"] < stats["mean"] < stats["ci_high"]
    assert sorted(p.name for p in (out / "tensorboard").iterdir()) == ["seed_3", "seed_4"]
    assert any((out / "tensorboard" / "seed_3").glob("events.out.tfevents.*"))
    assert (out / "checkpoints" / str(FINAL_STEPS)).is_dir()
    assert len(list((out / "checkpoints").iterdir())) == 3  # the last --keep-checkpoints


def test_the_recorded_commit_is_dirty_for_changed_code_but_not_for_changed_results(tmp_path):
    def git(*args: str) -> None:
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path,
                       check=True, capture_output=True)

    (tmp_path / "ccrjax").mkdir()
    (tmp_path / "experiments" / "results" / "search").mkdir(parents=True)
    code = tmp_path / "ccrjax" / "train.py"
    record = tmp_path / "experiments" / "results" / "search" / "invocations.json"
    code.write_text("x = 1\n")
    record.write_text("[]\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "first")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True,
                          text=True, check=True).stdout.strip()
    assert tree_commit(tmp_path) == head
    record.write_text("[1]\n")  # another program's invocation record: still clean
    (tmp_path / "notes.txt").write_text("untracked\n")
    assert tree_commit(tmp_path) == head
    code.write_text("x = 2\n")
    assert tree_commit(tmp_path) == head + "+dirty"
    assert tree_commit(tmp_path / "ccrjax" / "missing") is None
    # The code's commit, which a grid's checkpoint must match: results and documentation
    # committed later leave it; a code change moves it.
    code.write_text("x = 1\n")
    (tmp_path / "notes.txt").unlink()
    assert tree_code_commit(tmp_path) == head
    git("add", ".")
    git("commit", "-qm", "results")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "page.md").write_text("a page\n")
    (tmp_path / "README.md").write_text("readme\n")
    git("add", ".")
    git("commit", "-qm", "documentation")
    assert tree_commit(tmp_path) != head and tree_code_commit(tmp_path) == head
    # Tests and a module that only reports on finished cells do not train either.
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_x.py").write_text("def test(): pass\n")
    (tmp_path / "experiments" / "study_report.py").write_text("y = 1\n")
    git("add", ".")
    git("commit", "-qm", "tests and a report")
    assert tree_code_commit(tmp_path) == head
    (tmp_path / "experiments" / "study.py").write_text("z = 1\n")
    git("add", ".")
    git("commit", "-qm", "an experiment that trains")
    trains = tree_commit(tmp_path)
    assert tree_code_commit(tmp_path) == trains != head
    head = trains
    code.write_text("x = 3\n")
    assert tree_code_commit(tmp_path) == head + "+dirty"
    git("commit", "-qam", "code")
    assert tree_code_commit(tmp_path) == tree_commit(tmp_path) != head


def test_the_command_trains_what_the_library_trains(finished_run):
    """The run folder's curves are the pure program's evaluation history (both seeds
    vmapped, as the command trains them: on a GPU the kernels, and so the rounding, follow
    the batch's shape)."""
    spec = train.RunSpec.from_dict(RunFolder(finished_run).read_config()["run"])
    program = make_train(spec.train)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in (3, 4)])
    _, history = jax.jit(jax.vmap(program.train))(keys)
    rows = [r for r in read_metrics(finished_run / "metrics.csv") if r["seed"] == 4]
    np.testing.assert_allclose([r["return"] for r in rows], history["return"][1], rtol=1e-5)
    np.testing.assert_array_equal([r["env_steps"] for r in rows], history["env_steps"][1])


# ---------------------------------------------------------------------------- resuming
@pytest.mark.slow  # three processes; Ctrl-C's resume stays in make test (50 s)
def test_a_run_killed_with_sigkill_resumes_to_exactly_the_same_result(
    finished_run, tmp_path, subprocess_env, capsys
):
    out = tmp_path / "killed"
    process = start_subprocess(out, subprocess_env)
    wait_for(out / "checkpoints" / "400", process)
    process.kill()
    process.communicate()
    assert process.returncode == -signal.SIGKILL
    assert (out / "checkpoints").exists() and not (out / "summary.json").exists()
    status, _, err = run_main(train, ["--out", out, "--resume", "--no-progress", "--keep-buffer"],
                              capsys)
    assert status == 0, err
    assert "resuming" in err
    assert_same_run(finished_run, out)


def test_ctrl_c_saves_a_checkpoint_exits_cleanly_and_resumes_exactly(
    finished_run, tmp_path, subprocess_env, capsys
):
    out = tmp_path / "interrupted"
    process = start_subprocess(out, subprocess_env)
    wait_for(out / "checkpoints" / "400", process)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == train.INTERRUPTED, err
    assert "Traceback" not in err
    assert "--resume" in err
    saved = sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit())
    assert saved and saved[-1] >= 400
    rows = read_metrics(out / "metrics.csv")
    assert max(r["env_steps"] for r in rows) == saved[-1]  # the checkpoint holds every row
    status, _, err = run_main(train, ["--out", out, "--resume", "--no-progress", "--keep-buffer"],
                              capsys)
    assert status == 0, err
    assert_same_run(finished_run, out)


# A real process signals itself at one chosen moment: the driver wraps the function that
# runs then, so each test lands its Ctrl-C or SIGTERM where it means to, every time.
STOP_AT = """
import os, signal, sys
import jax
from ccrjax import evaluate, terminal, train
from ccrjax.run import session as sessions
from ccrjax.run.checkpoint import Checkpoints

command, moment, name, times, *argv = sys.argv[1:]


def stop():
    for _ in range(int(times)):
        os.kill(os.getpid(), getattr(signal, name))


def stopping_before(function):
    def wrapped(*args, **kwargs):
        stop()
        return function(*args, **kwargs)
    return wrapped


if moment == "compilation":
    terminal.compile_phase = stopping_before(terminal.compile_phase)
elif moment == "first-chunk":
    prepare = sessions.prepare

    def prepare_then_stop_in_the_first_chunk(*args, **kwargs):
        session = prepare(*args, **kwargs)
        chunk = session.chunk
        session.chunk = lambda state, learn: (stop() if learn else None, chunk(state, learn))[1]
        return session
    sessions.prepare = prepare_then_stop_in_the_first_chunk
elif moment == "checkpoint-write":
    save = Checkpoints.save

    def save_then_stop(self, *args, **kwargs):
        save(self, *args, **kwargs)  # the write goes on in orbax's threads
        stop()
    Checkpoints.save = save_then_stop
elif moment == "evaluation":
    jax.device_get = stopping_before(jax.device_get)
module = train if command == "train" else evaluate
sys.exit(module.main(argv))
"""


def stopped_at(moment: str, signal_name: str, times: int, argv, env, command: str = "train"):
    """Runs ``python -m ccrjax.<command> argv`` in a process that sends itself
    ``signal_name`` ``times`` times at ``moment``; returns its status and stderr."""
    result = subprocess.run(
        [sys.executable, "-c", STOP_AT, command, moment, signal_name, str(times),
         *map(str, argv)],
        capture_output=True, text=True, env=env, timeout=300,
    )
    return result.returncode, result.stderr


def checkpoint_steps(out: Path) -> list[int]:
    return RunFolder(out).checkpoint_steps()


def assert_stopped_cleanly(status: int, err: str, *fragments: str) -> None:
    """Status 130, no traceback, and each of ``fragments`` in the message."""
    assert status == train.INTERRUPTED, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, err


def resume_to_the_end(out: Path, capsys) -> str:
    """``--resume`` of the run in ``out`` to its end; returns what it printed to stderr."""
    status, _, err = run_main(train, ["--out", out, "--resume", "--no-progress",
                                      "--keep-buffer"], capsys)
    assert status == 0, err
    return err


@pytest.mark.slow  # two processes that compile a run (40 s)
def test_sigterm_during_compilation_exits_130_and_the_same_command_starts_over(
    finished_run, tmp_path, subprocess_env, capsys
):
    out = tmp_path / "compiling"
    status, err = stopped_at("compilation", "SIGTERM", 1, [*TINY, "--out", out],
                             subprocess_env)
    assert_stopped_cleanly(status, err,
                           "stopped by SIGTERM; no checkpoint was written")
    assert checkpoint_steps(out) == [] and (out / "config.json").exists()
    status, _, err = run_main(train, [*TINY, "--out", out], capsys)  # the same command
    assert status == 0, err
    assert "stopped before its first checkpoint; this run starts in its place" in err
    assert_same_run(finished_run, out)


@pytest.mark.slow
def test_a_second_ctrl_c_during_compilation_stops_at_once_and_resume_starts_over(
    finished_run, tmp_path, subprocess_env, capsys
):
    out = tmp_path / "twice"
    status, err = stopped_at("compilation", "SIGINT", 2, [*TINY, "--out", out], subprocess_env)
    assert_stopped_cleanly(status, err, "stopped by SIGINT; no checkpoint was written")
    assert "starts again from the beginning" in resume_to_the_end(out, capsys)
    assert_same_run(finished_run, out)


def test_ctrl_c_during_the_first_chunk_finishes_it_and_saves_a_checkpoint(
    tmp_path, subprocess_env
):
    out = tmp_path / "first-chunk"
    status, err = stopped_at("first-chunk", "SIGINT", 1, [*TINY, "--out", out],
                             subprocess_env)
    assert_stopped_cleanly(status, err, "finishing the current chunk", "checkpoint 200 is saved")
    assert checkpoint_steps(out) == [200]


@pytest.mark.slow
def test_a_second_sigterm_during_a_checkpoint_write_keeps_it_whole_and_resumes_exactly(
    finished_run, tmp_path, subprocess_env, capsys
):
    out = tmp_path / "writing"
    status, err = stopped_at("checkpoint-write", "SIGTERM", 2, [*TINY, "--out", out],
                             subprocess_env)
    assert_stopped_cleanly(status, err, "stopped by SIGTERM; at 200 steps per seed, "
                           "checkpoint 200 is saved")
    assert checkpoint_steps(out) == [200]
    resume_to_the_end(out, capsys)
    assert_same_run(finished_run, out)


def test_evaluate_stopped_during_evaluation_exits_130_and_writes_nothing(
    finished_run, tmp_path, subprocess_env
):
    out = tmp_path / "evaluating"
    shutil.copytree(finished_run, out)
    (out / "evaluation.json").unlink(missing_ok=True)
    status, err = stopped_at("evaluation", "SIGTERM", 1, [out, "--episodes", "4"],
                             subprocess_env, command="evaluate")
    assert_stopped_cleanly(status, err, "stopped by SIGTERM; the run's checkpoints are unchanged")
    assert not (out / "evaluation.json").exists()


def test_evaluate_of_a_run_without_checkpoint_prints_one_line_and_nothing_else(
    finished_run, tmp_path, subprocess_env
):
    out = tmp_path / "no-checkpoint"  # a run stopped before its first checkpoint
    out.mkdir()
    shutil.copy(finished_run / "config.json", out / "config.json")
    result = subprocess.run([sys.executable, "-m", "ccrjax.evaluate", str(out)],
                            capture_output=True, text=True, env=subprocess_env, timeout=300)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"python -m ccrjax.evaluate: error: {out} has no checkpoint yet"]


def test_an_unreadable_checkpoint_falls_back_to_the_previous_one(finished_run, tmp_path, capsys):
    out = tmp_path / "corrupted"
    shutil.copytree(finished_run, out)
    # A half-written checkpoint (what a kill during a save leaves) is ignored ...
    (out / "checkpoints" / "9999.orbax-checkpoint-tmp").mkdir()
    # ... and a corrupted one is set aside, the previous one used.
    latest = out / "checkpoints" / str(FINAL_STEPS)
    for data in latest.rglob("*"):
        if data.is_file() and data.stat().st_size > 0:
            data.write_bytes(b"\0" * 7)
    status, _, err = run_main(train, ["--out", out, "--resume", "--no-progress", "--keep-buffer"],
                              capsys)
    assert status == 0, err
    assert f"checkpoint {FINAL_STEPS} is unreadable" in err
    assert f"fell back to checkpoint {FINAL_STEPS - 200}" in err
    # Only the latest checkpoint keeps a replay buffer: the fallback resumes without one,
    # and says so; everything else it restores.
    assert f"checkpoint {FINAL_STEPS - 200:,} kept no replay buffer" in err
    restored = final_state(out)
    assert restored.step == FINAL_STEPS and restored.buffer is not None
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["per_seed"]) == {"3", "4"}


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--scenario", "lava"], "--scenario"),
        (["--algo", "ppo"], "--algo"),
        (["--frobnicate", "3"], "--frobnicate"),
        (["--seeds", "0"], "--seeds"),
        (["--steps", "many"], "--steps"),
        (["--lam", "-1", "--variant", "ccr"], "--lam"),
        (["--variant", "ccr", "--ccr-degree", "9"], "degree"),
        (["--variant", "ccr", "--ccr-window", "-1"], "window"),
        (["--variant", "ccr", "--ccr-comm-range", "-0.5"], "--ccr-comm-range must be"),
        (["--variant", "plain", "--lam", "3"], "--lam applies to --variant ccr"),
        (["--robots", "1"], "--robots"),
        (["--ddpg-actor-lr", "-0.1"], "--ddpg-actor-lr must be"),
        (["--ddpg-critic-hidden", "64,0"], "--ddpg-critic-hidden"),
        (["--ddpg-gamma", "1.5"], "--ddpg-gamma must be"),
        (["--algo", "maac", "--maac-action-set", "x"], "--maac-action-set must be one of"),
        (["--compilation-cache", "/dev/null"], "--compilation-cache /dev/null is a file"),
        (["--penalty", "2"], "--penalty"),
        (["--maac-policy-lr", "0.01"], "--maac"),
        (["--algo", "maac", "--ddpg-tau", "0.1"], "--ddpg"),
        (["--resume"], "--out"),
        # A budget that ends before learning starts (25,600 transitions) learns nothing.
        (["--steps", "20000"], "(--steps) 20,000 ends before learning starts: at least 25,600"),
        (["--steps", "30000", "--learning-starts", "40000"], "at least 40,000"),
        (["--variant", "lagrangian", "--cost-limit", "1.5"], "--cost-limit: must be in [0.0, 1.0]"),
        (["--variant", "lagrangian", "--cost-limit", "inf"], "--cost-limit: must be finite"),
        (["--variant", "ccr", "--cost-limit", "0.1"], "applies to --variant lagrangian"),
        (["--variant", "plain", "--cost-limit", "0.1"], "lagrangian, not plain"),
        (["--variant", "lagrangian", "--lagrange-kp", "-1"], "--lagrange-kp must be a finite"),
        (["--variant", "lagrangian", "--lagrange-ki", "nan"], "--lagrange-ki: must be finite"),
        (["--variant", "lagrangian", "--lagrange-cap", "0"], "--lagrange-cap must be a finite"),
        (["--variant", "lagrangian", "--lagrange-controller", "bang"], "--lagrange-controller"),
        (["--variant", "plain", "--lagrange-kd", "1"], "--lagrange"),
    ],
)
def test_bad_command_lines_get_one_line_and_status_2(argv, fragment, tmp_path, capsys):
    out = tmp_path / "never"
    status, _, err = run_main(train, [*argv, "--out", out] if argv != ["--resume"] else argv,
                              capsys)
    assert_usage_error(status, err, fragment)
    assert not out.exists() or not any(out.iterdir())


def test_a_folder_holding_a_run_is_never_overwritten(finished_run, tmp_path, capsys):
    out = tmp_path / "existing"
    shutil.copytree(finished_run, out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    status, _, err = run_main(train, [*TINY, "--lam", "3", "--variant", "ccr", "--out", out],
                              capsys)
    assert_usage_error(status, err)
    status, _, err = run_main(train, [*TINY, "--out", out], capsys)
    assert_usage_error(status, err, "already holds a run", "--resume")
    assert before == {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    status, _, err = run_main(train, [*TINY, "--out", other], capsys)
    assert_usage_error(status, err, "not an empty folder")
    assert (other / "notes.txt").read_text() == "mine"


def test_resume_needs_a_run_folder(tmp_path, capsys):
    status, _, err = run_main(train, ["--out", tmp_path / "nothing", "--resume"], capsys)
    assert_usage_error(status, err, "holds no run")


def test_resume_refuses_options_that_contradict_the_run(finished_run, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    status, _, err = run_main(train, ["--out", out, "--resume", "--penalty", "2"], capsys)
    assert_usage_error(status, err, "penalty is 1.0 in the run, 2.0 here")
    status, _, err = run_main(train, ["--out", out, "--resume", "--seeds", "5"], capsys)
    assert_usage_error(status, err, "seeds is 2 in the run, 5 here")


def test_a_checkpoint_of_another_configuration_is_refused(finished_run, tmp_path, capsys):
    out = tmp_path / "mixed"
    shutil.copytree(finished_run, out)
    folder = RunFolder(out)
    record = folder.read_config()
    record["run"]["train"]["transform"]["penalty"] = 2.0  # same shapes, another run
    record["fingerprint"] = fingerprint(record["run"])
    folder.write_config(record)
    status, _, err = run_main(train, ["--out", out, "--resume"], capsys)
    assert_usage_error(status, err, "another configuration")


def test_a_folder_that_cannot_be_written_is_refused(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    status, _, err = run_main(train, [*TINY, "--out", blocker / "run"], capsys)
    assert_usage_error(status, err, "cannot write")


def test_a_run_that_turns_non_finite_stops_naming_the_iteration(tmp_path, capsys):
    out = tmp_path / "exploding"
    # Learning starts in the second chunk (400 transitions, 20 per iteration, 10 iterations
    # per chunk), after the first checkpoint; Adam steps of 1e30 make the critic's output
    # overflow on the next update.
    argv = [*TINY, "--learning-starts", "400", "--ddpg-critic-lr", "1e30", "--ddpg-actor-lr",
            "1e30", "--out", out]
    status, _, err = run_main(train, argv, capsys)
    assert status == train.NONFINITE, err
    assert "Traceback" not in err
    assert "non-finite at iteration" in err
    assert "last good checkpoint" in err
    kept = sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit())
    assert kept and kept[-1] < FINAL_STEPS
    restored = final_state(out)
    assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(restored.state))
    assert int(np.max(restored.state.nonfinite_iteration)) == -1


# ---------------------------------------------------------------------------- evaluate
def test_evaluate_reloads_the_run_and_redraws_its_pictures(finished_run, tmp_path, capsys):
    out = tmp_path / "evaluated"
    shutil.copytree(finished_run, out)
    (out / "episode.png").unlink()
    status, printed, err = run_main(evaluate, [out, "--episodes", "8"], capsys)
    assert status == 0, err
    assert "success_rate" in printed and "danger_frequency" in printed
    assert (out / "episode.png").stat().st_size > 0
    result = json.loads((out / "evaluation.json").read_text())
    assert result["checkpoint_env_steps"] == FINAL_STEPS
    assert result["episodes_per_seed"] == 8
    assert set(result["per_seed"]) == {"3", "4"}
    status, _, err = run_main(evaluate, [tmp_path / "nowhere"], capsys)
    assert_usage_error(status, err, "holds no run")
    status, _, err = run_main(evaluate, [out, "--episodes", "0"], capsys)
    assert_usage_error(status, err, "--episodes")


# ---------------------------------------------------------------------------- the policy
def test_the_exported_policy_acts_as_the_trained_learner(finished_run, tmp_path):
    """``ccrjax.load_policy`` needs only the run's policy export and config: its actions are
    the trained learner's deterministic actions, for every seed (and not another seed's)."""
    import ccrjax

    copy = tmp_path / "policy-only"
    copy.mkdir()
    shutil.copytree(finished_run / "policy", copy / "policy")
    shutil.copy(finished_run / "config.json", copy / "config.json")  # no checkpoints
    restored = final_state(finished_run)
    spec = train.RunSpec.from_dict(RunFolder(finished_run).read_config()["run"])
    program = make_train(spec.train)
    obs = jax.random.normal(jax.random.PRNGKey(7), (6, spec.train.num_robots, program.obs_size))
    for index, seed in enumerate(spec.seed_list):
        act = ccrjax.load_policy(copy, seed=seed)
        learner = jax.tree_util.tree_map(lambda x, i=index: x[i], restored.state.learner)
        expected = program.learner.act(learner, obs, jax.random.PRNGKey(0), False)
        # The same parameters; jit may round the last bit differently from eager mode.
        np.testing.assert_allclose(np.asarray(act(obs)), np.asarray(expected), rtol=1e-5,
                                   atol=1e-6)
    first, second = (ccrjax.load_policy(copy, seed=s)(obs) for s in spec.seed_list)
    assert not np.allclose(np.asarray(first), np.asarray(second))
    size = sum(f.stat().st_size for f in (copy / "policy").rglob("*") if f.is_file())
    assert size < 1_000_000  # small: networks only, no replay buffer
    first_act = ccrjax.load_policy(copy, seed=spec.seed_list[0])
    np.testing.assert_allclose(np.asarray(jax.vmap(first_act)(obs)), np.asarray(first),
                               rtol=1e-5, atol=1e-6)  # one team at a time, under vmap
    with pytest.raises(ValueError, match=r"obs must be \[batch, "):
        first_act(obs[..., :-1])  # one feature short
    # The whole team (here the pessimistic transform's penalty too) evaluates as the run did.
    key = jax.random.PRNGKey(11)
    expected = program.evaluate(jax.tree_util.tree_map(lambda x: x[1], restored.state), key)
    got = ccrjax.load_team(copy, seed=spec.seed_list[1]).evaluate(key)
    for name, value in expected.items():
        np.testing.assert_allclose(np.asarray(got[name]), np.asarray(value), rtol=1e-5,
                                   atol=1e-6, err_msg=name)
    with pytest.raises(ValueError, match="seed must be one of"):
        ccrjax.load_policy(copy, seed=99)
    with pytest.raises(FileNotFoundError, match="no exported policy"):
        ccrjax.load_policy(tmp_path)


def test_every_option_says_what_it_is():
    """Each option of the train command has a help text beyond its default; the nested
    configurations' texts come from their fields' comments."""
    parser = train.build_parser()
    for action in parser._actions:
        if not action.option_strings or action.help == "==SUPPRESS==":
            continue
        text = (action.help or "").split("(default")[0].strip()
        assert len(text) > 5, f"{action.option_strings[0]} has no help text"
    helps = {a.option_strings[0]: a.help for a in parser._actions if a.option_strings}
    assert helps["--maac-reward-scale"].startswith("entropy temperature is 1 / reward_scale")


def test_only_the_latest_checkpoint_keeps_a_replay_buffer(finished_run, tmp_path, capsys):
    """Older checkpoints keep parameters, optimiser states and counters, not the replay
    buffer; a finished run drops even its last one unless --keep-buffer (finished_run kept
    it), and the end of a run prints the folder's size."""
    steps = sorted(int(p.name) for p in (finished_run / "checkpoints").iterdir()
                   if p.name.isdigit())
    assert len(steps) == 3
    with_buffer = [s for s in steps if (finished_run / "checkpoints" / str(s) / "buffer").is_dir()]
    assert with_buffer == [FINAL_STEPS]
    out = tmp_path / "dropped"
    shutil.copytree(finished_run, out)
    before = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    status, printed, err = run_main(train, ["--out", out, "--resume", "--no-progress"], capsys)
    assert status == 0, err
    assert "replay buffer" in err and "is not kept" in err
    assert not any((out / "checkpoints" / str(s) / "buffer").exists() for s in steps)
    after = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    assert after < before
    assert "MiB" in printed and "the folder holds" in printed
    # A finished run resumed at its budget trains nothing and rewrites nothing.
    assert "is finished" in printed and "nothing to train" in printed
    assert (out / "summary.json").read_text() == (finished_run / "summary.json").read_text()
    assert read_metrics(out / "metrics.csv") == read_metrics(finished_run / "metrics.csv")
    # Everything but the buffer still restores; evaluation needs no buffer.
    restored = final_state(out)
    assert restored.step == FINAL_STEPS and restored.buffer is None
    status, _, err = run_main(evaluate, [out, "--episodes", "2", "--no-pictures"], capsys)
    assert status == 0, err


@pytest.mark.slow
def test_a_finished_run_extends_exactly_as_if_started_with_the_larger_budget(
        finished_run, tmp_path, capsys):
    """``--resume --steps N`` with N above the budget: the run goes on from its last
    checkpoint (its replay buffer grown as a longer run's would be) and ends exactly where
    a run started with N ends; the extension is recorded. A smaller N is refused."""
    extended = tmp_path / "extended"
    shutil.copytree(finished_run, extended)
    longer = FINAL_STEPS + 400
    (extended / "evaluation.json").write_text(json.dumps({"checkpoint_env_steps": FINAL_STEPS}))
    status, printed, err = run_main(train, ["--out", extended, "--resume", "--steps", longer,
                                            "--no-progress", "--keep-buffer"], capsys)
    assert status == 0, err
    assert "extending the run" in err
    # python -m ccrjax.evaluate's file of the shorter run is named as such.
    assert f"evaluation.json evaluated the checkpoint at {FINAL_STEPS:,} steps" in printed
    record = json.loads((extended / "config.json").read_text())
    assert record["run"]["train"]["total_env_steps"] == longer
    assert record["extensions"][0]["from_total_env_steps"] == FINAL_STEPS
    assert record["extensions"][0]["runs_as_total_env_steps"] == longer
    assert record["extensions"][0]["replay_buffer"].startswith("in the last checkpoint")
    fresh = tmp_path / "fresh"
    tiny = [str(a) for a in TINY]
    tiny[tiny.index("--steps") + 1] = str(longer)
    status, _, err = run_main(train, [*tiny, "--out", fresh], capsys)
    assert status == 0, err
    a, b = final_state(extended), final_state(fresh)
    assert a.step == b.step == longer
    for x, y in zip(jax.tree_util.tree_leaves((a.state, a.buffer)),
                    jax.tree_util.tree_leaves((b.state, b.buffer)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    rows_a, rows_b = read_metrics(extended / "metrics.csv"), read_metrics(fresh / "metrics.csv")
    assert [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows_a] == [
        {k: v for k, v in r.items() if k != "wall_time_s"} for r in rows_b]
    status, _, err = run_main(train, ["--out", extended, "--resume", "--steps", 1000], capsys)
    assert_usage_error(status, err, "extended, not shortened")
    # An extension that rounds says so; resuming the finished run afterwards repeats the
    # note only where the command names --steps again.
    rounded = longer + 1
    resume = ["--out", extended, "--resume", "--no-progress"]
    status, _, err = run_main(train, [*resume, "--steps", rounded], capsys)
    assert status == 0 and f"note: --steps {rounded:,} runs as" in err, err
    status, printed, err = run_main(train, resume, capsys)
    assert status == 0 and "is finished" in printed and "note:" not in err, err
    status, printed, err = run_main(train, [*resume, "--steps", rounded], capsys)
    assert status == 0 and "is finished" in printed and f"--steps {rounded:,} runs as" in err


@pytest.mark.slow
def test_a_lagrangian_run_records_its_multiplier_and_resumes_exactly(tmp_path, capsys):
    """``--variant lagrangian --cost-limit``: the multiplier's path and its input are columns
    of metrics.csv and panels of the curves; a run stopped half way and resumed (multiplier
    state, cost channel of the buffer and all) ends exactly where the straight run ends."""
    tiny = [str(a) for a in TINY]
    tiny[tiny.index("--variant") + 1] = "lagrangian"
    tiny += ["--cost-limit", "0.001", "--lagrange-ki", "1"]
    straight, cut = tmp_path / "straight", tmp_path / "cut"
    status, _, err = run_main(train, [*tiny, "--out", straight], capsys)
    assert status == 0, err
    half = [*tiny, "--out", cut]
    half[half.index("--steps") + 1] = str(FINAL_STEPS // 2)
    status, _, err = run_main(train, half, capsys)
    assert status == 0, err
    status, _, err = run_main(train, ["--out", cut, "--resume", "--steps", FINAL_STEPS,
                                      "--keep-buffer"], capsys)
    assert status == 0, err
    a, b = final_state(straight), final_state(cut)
    assert a.step == b.step == FINAL_STEPS and a.buffer.cost is not None
    for x, y in zip(jax.tree_util.tree_leaves((a.state, a.buffer)),
                    jax.tree_util.tree_leaves((b.state, b.buffer)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    rows = read_metrics(straight / "metrics.csv")
    assert [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows] == [
        {k: v for k, v in r.items() if k != "wall_time_s"}
        for r in read_metrics(cut / "metrics.csv")]
    assert {"lagrange_multiplier", "lagrange_cost"} <= set(rows[0])
    assert rows[0]["lagrange_multiplier"] == 0.0 and rows[-1]["lagrange_multiplier"] > 0.0
    summary = json.loads((straight / "summary.json").read_text())
    assert summary["per_seed"]["3"]["lagrange_multiplier"] == rows[-2]["lagrange_multiplier"]
    assert (straight / "curves.png").stat().st_size > 0
    spec = train.RunSpec.from_dict(RunFolder(straight).read_config()["run"])
    obs = jnp.zeros((5, spec.train.num_robots, make_train(spec.train).obs_size))
    act = ccrjax.load_policy(straight, seed=3)  # the exported policy of a Lagrangian run
    assert act(obs).shape == (5, spec.train.num_robots, 2)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["ccr", "lagrangian"])
def test_a_mappo_run_resumes_exactly_and_loads(variant, tmp_path, capsys):
    """An on-policy run (MAPPO with CCR, or with the Lagrangian's cost channel) stopped half
    way and resumed ends exactly where the straight run ends; its policy and team load."""
    tiny = ["--scenario", "hidden_obstacle", "--algo", "mappo", "--variant", variant,
            "--steps", "800", "--num-envs", "4", "--episode-length", "10", "--eval-every",
            "200", "--eval-episodes", "4", "--ppo-actor-hidden", "16", "--ppo-critic-hidden",
            "16", "--seeds", "2", "--seed-offset", "3", "--checkpoint-every", "200",
            "--no-progress"]
    if variant == "lagrangian":
        tiny += ["--cost-limit", "0.001", "--lagrange-ki", "1"]
    straight, cut = tmp_path / "straight", tmp_path / "cut"
    status, _, err = run_main(train, [*tiny, "--out", straight], capsys)
    assert status == 0, err
    half = [*tiny, "--out", cut]
    half[half.index("--steps") + 1] = "400"
    status, _, err = run_main(train, half, capsys)
    assert status == 0, err
    status, _, err = run_main(train, ["--out", cut, "--resume", "--steps", 800], capsys)
    assert status == 0, err
    a, b = final_state(straight), final_state(cut)
    assert a.step == b.step == 800
    for x, y in zip(jax.tree_util.tree_leaves(a.state), jax.tree_util.tree_leaves(b.state),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert [{k: v for k, v in r.items() if k != "wall_time_s"}
            for r in read_metrics(straight / "metrics.csv")] == [
        {k: v for k, v in r.items() if k != "wall_time_s"}
        for r in read_metrics(cut / "metrics.csv")]
    spec = train.RunSpec.from_dict(RunFolder(straight).read_config()["run"])
    assert spec.train.num_envs == 4 and spec.train.resolved_learner.centralised_critic
    obs = jnp.zeros((5, spec.train.num_robots, make_train(spec.train).obs_size))
    act = ccrjax.load_policy(straight, seed=4)
    assert act(obs).shape == (5, spec.train.num_robots, 2)
    team = ccrjax.load_team(straight, seed=4)
    assert 0.0 <= float(team.evaluate(jax.random.PRNGKey(1))["success_rate"]) <= 1.0


def test_a_run_is_finished_only_once_its_summary_and_policy_are_written(finished_run, tmp_path):
    """A run stopped while finishing (no exported policy yet), or an extension stopped
    before its summary (the summary of the shorter run), resumes instead of being taken
    for finished."""
    out = tmp_path / "finishing"
    shutil.copytree(finished_run, out)
    folder = RunFolder(out)
    spec = train.RunSpec.from_dict(folder.read_config()["run"])
    assert train.finished(folder, spec)
    summary = json.loads((out / "summary.json").read_text())
    (out / "summary.json").write_text(json.dumps({**summary, "env_steps_per_seed": 200}))
    assert not train.finished(folder, spec)
    (out / "summary.json").write_text(json.dumps(summary))
    (out / "policy" / "policy.json").unlink()
    assert not train.finished(folder, spec)


def test_a_state_larger_than_the_memory_that_holds_it_is_refused_before_training(
        tmp_path, capsys, monkeypatch):
    """The memory is the accelerator's where JAX reports one (a GPU holds the training
    state), else this machine's; a state that does not fit twice gets one line before
    anything trains, and leaves no run behind."""
    class Host:  # the CPU reports no limit
        device_kind = "cpu"

        def memory_stats(self):
            return None

    class Accelerator:
        device_kind = "NVIDIA H100 80GB HBM3"

        def memory_stats(self):
            return {"bytes_limit": 80 * 2**30, "bytes_in_use": 0}

    monkeypatch.setattr(sessions.jax, "devices", lambda *_: [Host()])
    assert sessions.training_memory() == (sessions.physical_memory(), "this machine")
    monkeypatch.setattr(sessions.jax, "devices", lambda *_: [Accelerator()])
    assert sessions.training_memory() == (80 * 2**30, "the NVIDIA H100 80GB HBM3")
    monkeypatch.undo()
    monkeypatch.setattr(sessions, "training_memory", lambda: (2**20, "the tiny device"))
    out = tmp_path / "too-big"
    status, _, err = run_main(train, [*TINY, "--out", out], capsys)
    assert_usage_error(status, err, "needs", "GiB (twice that while training) but the tiny "
                       "device has 0.0 GiB", "--seeds")
    assert not (out / "config.json").exists() and not (out / "checkpoints").exists()


def test_a_request_after_the_runs_last_check_still_exits_130_saying_all_is_written(capsys):
    """Ctrl-C in the moment between a finished run's last check and the command's exit: no
    promise of work still to come, and the command ends with 130 and one closing line."""
    before = signal.getsignal(signal.SIGINT)
    with terminal.stopping("prog") as stop:
        stop.phase = "done"
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.requested
        time.sleep(0.2)  # the watcher thread has seen it too, and said nothing
        assert capsys.readouterr().err == ""
        assert stop.closing(0) == 130
        assert stop.closing(2) == 2
    err = capsys.readouterr().err
    assert err.strip() == "prog: stopped by SIGINT after the work finished; everything is written"
    with terminal.stopping("prog") as stop:
        assert stop.closing(0) == 0
    assert signal.getsignal(signal.SIGINT) is before  # given back
