"""Ctrl-C and SIGTERM (ccrjax.terminal), in real processes of every command: from the
command's first statement to the end of compilation (imports, set-up, tracing, compiling) a
signal ends it at once with status 130 and one line, never a traceback and never a run
trained to its end; while training, a second signal ends the process within seconds
however long the chunk in flight, keeping the last whole checkpoint, from which
``--resume`` is exact."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_train_command import TINY, assert_same_run, checkpoint_steps, finished_run, run_main

from ccrjax import train

ROOT = Path(__file__).resolve().parents[1]
__all__ = ["finished_run"]  # the fixture, shared with test_train_command

pytestmark = pytest.mark.slow


def fresh_env(cache: Path) -> dict[str, str]:
    """No compilation cache to find: every process compiles from scratch."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(XDG_CACHE_HOME=str(cache), PYTHONUNBUFFERED="1")
    return env


def caught(pid: int) -> set[int]:
    """The signals process ``pid`` handles (``SigCgt`` in Linux's ``/proc/<pid>/status``)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:  # it has ended
        return set()
    mask = int(next(line for line in status.splitlines() if line.startswith("SigCgt:"))
               .split()[1], 16)
    return {number for number in range(1, 65) if mask >> (number - 1) & 1}


def installed(process: subprocess.Popen, timeout: float = 120.0) -> None:
    """Waits for the command's first statement, ``terminal.install``. The interpreter
    never handles SIGTERM itself and install takes it last, with the signals held until
    everything is in place, so a signal sent once SIGTERM is handled is the command's.
    Before that is the interpreter's own start-up, which no program can answer."""
    if not Path("/proc/self/status").exists():
        pytest.skip("needs Linux's /proc to see when a process installs its handlers")
    began = time.monotonic()
    while signal.SIGTERM not in caught(process.pid):
        if process.poll() is not None or time.monotonic() - began > timeout:
            break
        time.sleep(0.002)


def signalled(argv: list[str], delay: float, cache: Path,
              name: str = "SIGINT") -> tuple[int | None, str, float]:
    """Starts ``argv`` and sends ``name`` ``delay`` seconds after the command's first
    statement; returns its status, stderr and the seconds it took to end after the signal
    (``None`` if it ended before it)."""
    process = subprocess.Popen(argv, cwd=ROOT, env=fresh_env(cache), text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    installed(process)
    time.sleep(delay)
    if process.poll() is not None:
        return None, process.communicate()[1], 0.0
    sent = time.monotonic()
    process.send_signal(getattr(signal, name))
    _, err = process.communicate(timeout=120)
    return process.returncode, err, time.monotonic() - sent


def assert_one_line_stop(status: int | None, err: str, prog: str, name: str = "SIGINT"):
    assert status == 130, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"{prog}: stopped by {name}; "), err


def test_train_stopped_at_any_moment_before_training_exits_130_in_one_line(tmp_path: Path):
    """The moments are spread over the time a reference process takes from its first
    statement to the end of its compilation, measured first, alike on any machine. On a
    loaded machine a process may compile sooner than the reference did, so a late moment can
    fall after its compilation: that stop is either the training stop (the chunk finished, a
    checkpoint kept) or, in the instant between compilation and the first chunk, the stop
    before training (no checkpoint, the one line); each is checked as such, and at least the
    first moments must fall before compilation ends."""
    command = [sys.executable, "-m", "ccrjax.train", *TINY, "--no-compilation-cache"]
    reference = subprocess.Popen([*command, "--out", str(tmp_path / "reference")], cwd=ROOT,
                                 env=fresh_env(tmp_path / "c"), text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    installed(reference)
    began = time.monotonic()
    for line in reference.stderr:
        if "compiled in" in line:
            compiled = time.monotonic() - began
            break
    reference.kill()
    reference.communicate()
    before_training = 0
    for fraction in (0.01, 0.05, 0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9):
        out = tmp_path / f"at-{fraction}"
        status, err, took = signalled([*command, "--out", str(out)], fraction * compiled,
                                      tmp_path / f"cache-{fraction}")
        assert not (out / "summary.json").exists(), fraction
        if "compiled in" in err:  # this process compiled before the moment came
            last = err.strip().splitlines()[-1]
            assert status == 130 and "Traceback" not in err, err
            if last.startswith("python -m ccrjax.train: stopped by SIGINT at "):
                assert checkpoint_steps(out), fraction  # the training stop
            else:  # between compilation and the first chunk: the stop before training
                assert_one_line_stop(status, err, "python -m ccrjax.train")
                assert took < 10, (fraction, took)
                assert checkpoint_steps(out) == []
            continue
        before_training += 1
        assert_one_line_stop(status, err, "python -m ccrjax.train")
        assert took < 10, (fraction, took)
        assert checkpoint_steps(out) == []
    assert before_training >= 5, before_training


@pytest.mark.parametrize("command", ["evaluate", "sweep", "demo", "search"])
def test_every_command_stopped_early_exits_130_in_one_line(command, finished_run,
                                                           tmp_path: Path):
    argv, prog = {
        "evaluate": ([sys.executable, "-m", "ccrjax.evaluate", str(finished_run),
                      "--episodes", "4"], "python -m ccrjax.evaluate"),
        "sweep": ([sys.executable, "-m", "ccrjax.sweep", "--variant", "pessimistic",
                   "--values", "0", "1", "--seeds", "2", "--steps", "2000",
                   "--learning-starts", "400", "--out", str(tmp_path / "sweep")],
                  "python -m ccrjax.sweep"),
        "demo": ([sys.executable, "-m", "ccrjax.demo", "--out", str(tmp_path / "demo")],
                 "python -m ccrjax.demo"),
        "search": ([sys.executable, "experiments/search.py", "--variant", "pessimistic",
                    "--quick", "--scenarios", "turbulence", "--algos", "iddpg", "--out",
                    str(tmp_path / "search")], "python experiments/search.py"),
    }[command]
    for delay in (0.0, 0.1, 0.5, 1.5, 3.0):
        status, err, took = signalled(argv, delay, tmp_path / f"cache-{delay}")
        assert_one_line_stop(status, err, prog)
        assert took < 10, (delay, took)


# The second chunk stands in for one of hours: it sleeps (as XLA does, without Python's
# lock) after two SIGTERMs are sent.
LONG_CHUNK = """
import os, signal, sys, time
from ccrjax import train
from ccrjax.run import session as sessions

prepare = sessions.prepare
calls = []


def prepare_with_a_long_second_chunk(*args, **kwargs):
    session = prepare(*args, **kwargs)
    chunk = session.chunk

    def long(state, learn):
        if learn:
            calls.append(True)
            if len(calls) == 2:
                session.checkpoints.wait()  # the first chunk's checkpoint is on disk
                print("SENDING", time.monotonic(), file=sys.stderr, flush=True)
                for _ in range(2):
                    os.kill(os.getpid(), signal.SIGTERM)
                    time.sleep(0.2)
                time.sleep(600)
        return chunk(state, learn)
    session.chunk = long
    return session


sessions.prepare = prepare_with_a_long_second_chunk
sys.exit(train.main(sys.argv[1:]))
"""


def test_a_second_signal_ends_a_long_chunk_within_seconds_and_resume_is_exact(
        finished_run, tmp_path: Path, subprocess_env, capsys):
    out = tmp_path / "long"
    done = subprocess.run([sys.executable, "-c", LONG_CHUNK, *TINY, "--out", str(out)],
                          capture_output=True, text=True, env=subprocess_env, timeout=300)
    ended = time.monotonic()
    err = done.stderr
    assert_one_line_stop(done.returncode, err, "python -m ccrjax.train", "SIGTERM")
    sent = float(next(line for line in err.splitlines() if line.startswith("SENDING")).split()[1])
    assert ended - sent < 15, err
    assert "at 200 steps per seed, checkpoint 200 is saved" in err.splitlines()[-1]
    assert checkpoint_steps(out) == [200]
    status, _, err = run_main(train, ["--out", out, "--resume", "--no-progress",
                                      "--keep-buffer"], capsys)
    assert status == 0, err
    assert_same_run(finished_run, out)
