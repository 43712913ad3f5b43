"""Several processes training one grid (``jax.distributed``, :mod:`ccrjax.run.distributed`):
mistakes are one line and exit status 2 before anything trains; two processes on this
machine make the same cells as one process over the same two devices, bit for bit, and
after one of them is killed the same command resumes to the same cells."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

# Processes that start JAX and compile: a minute or more, so `make test-slow`.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
TABLES = [sys.executable, str(ROOT / "experiments" / "tables.py")]
# Two programs of the quick tables (plain and pessimistic; CCR), 20 evaluations each (a
# kill can fall within a program), checkpointed after every one.
GRID = ["--quick", "--steps", "4000", "--scenarios", "hidden_obstacle", "--algos", "iddpg",
        "--checkpoint-minutes", "0.000001"]
# What a cell records about where and when it was made, not what it holds.
MADE = ("device", "commit", "date", "train_seconds_of_program", "compile_seconds_of_program")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def processes(out: Path, count: int, port: int, *extra: str, ids: range | None = None,
              env: dict | None = None) -> list[subprocess.Popen]:
    return [subprocess.Popen(
        [*TABLES, *GRID, "--out", str(out), "--coordinator", f"127.0.0.1:{port}",
         "--num-processes", str(count), "--process-id", str(i), *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=env) for i in (ids if ids is not None else range(count))]


def finished(started: list[subprocess.Popen], timeout: float = 900) -> list[tuple]:
    return [(p.wait(timeout), *p.communicate()) for p in started]


def refused(*args: str) -> str:
    """The one line a command with ``args`` ends with, having exited 2."""
    result = subprocess.run([*TABLES, *GRID, "--out", "/tmp/never-made", *args], cwd=ROOT,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert not Path("/tmp/never-made").exists()
    return result.stderr


def test_what_does_not_add_up_is_one_line_before_anything_trains():
    port = str(free_port())
    assert "--num-processes, --process-id missing" in refused("--coordinator", f"x:{port}")
    assert "must be 0 to 1" in refused("--coordinator", f"x:{port}", "--num-processes", "2",
                                       "--process-id", "2")
    assert "give HOST:PORT" in refused("--coordinator", "localhost", "--num-processes", "2",
                                       "--process-id", "1")
    assert "not both" in refused("--distributed", "--coordinator", f"x:{port}",
                                 "--num-processes", "2", "--process-id", "1")
    alone = ("--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
             "--distributed-timeout", "2")
    assert "not reachable within 2 s" in refused(*alone, "--process-id", "1")
    assert "1 of 2 processes came within 2 s" in refused(*alone, "--process-id", "0")


def test_counts_that_differ_are_named_in_every_process(tmp_path):
    port = free_port()
    host = processes(tmp_path, 2, port, "--distributed-timeout", "20", ids=range(1))
    time.sleep(1)
    other = subprocess.Popen(
        [*TABLES, *GRID, "--out", str(tmp_path), "--coordinator", f"127.0.0.1:{port}",
         "--num-processes", "3", "--process-id", "1", "--distributed-timeout", "20"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for status, _, err in finished([*host, other], timeout=120):
        assert status == 2 and err.count("\n") == 1
        assert "says --num-processes 3, process 0 2" in err


def cells(out: Path) -> dict[str, dict]:
    found = {}
    for path in sorted((out / "cells").glob("*.json")):
        cell = json.loads(path.read_text())
        found[path.name] = {k: v for k, v in cell.items() if k not in MADE}
    return found


def test_two_processes_make_one_process_cells_and_resume_after_a_kill(tmp_path):
    one = tmp_path / "one"
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    single = subprocess.run([*TABLES, *GRID, "--out", str(one)], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=900)
    assert single.returncode == 0, single.stderr
    reference = cells(one)
    assert len(reference) == 3  # plain, pessimistic, CCR

    two = tmp_path / "two"
    for status, _, err in finished(processes(two, 2, free_port())):
        assert status == 0, err
    assert cells(two) == reference  # bit for bit: every number as JSON writes it
    devices = {json.loads(p.read_text())["device"] for p in (two / "cells").glob("*.json")}
    assert devices == {"cpu:cpu x2"}
    assert not (two / "tables.md").exists()  # a part of the grid: no tables yet

    killed = tmp_path / "killed"
    started = processes(killed, 2, free_port())
    deadline = time.monotonic() + 900
    # The second program has a whole checkpoint (orbax renames it to its step when every
    # process's share is written).
    while not [step for step in (killed / "partial").glob("hidden_obstacle-iddpg-ccr/*")
               if step.name.isdigit()]:
        assert time.monotonic() < deadline and started[1].poll() is None
        time.sleep(0.2)
    started[1].send_signal(signal.SIGKILL)
    for process in started:
        try:
            process.wait(120)  # process 0 ends once its peer is gone
        except subprocess.TimeoutExpired:
            process.kill()
        process.communicate()
    assert list((killed / "partial").iterdir())
    results = finished(processes(killed, 2, free_port()))
    for status, _, err in results:
        assert status == 0, err
    assert "resuming from its checkpoint" in results[0][2]
    assert cells(killed) == reference
