"""The commands at a tiny size: ``evaluate`` reproduces the library's numbers, a resumed run
is exactly the uninterrupted one, ``sweep`` and ``demo`` write sane outputs.

One tiny training configuration (2 seeds, 2 environments of 10 steps, 8-unit networks,
two chunks of 200 steps) serves the in-process runs; the session's compilation cache
(``conftest.py``) serves the repeated compilations and the subprocesses.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax import evaluate, sweep, terminal, train
from ccrjax.run.checkpoint import Checkpoints
from ccrjax.run.folder import EVAL_METRICS, METRIC_RANGES, RunFolder, fingerprint, read_metrics
from ccrjax.run.stats import mean_ci
from ccrjax.training import make_train
from ccrjax.training.acting import episode_metrics, run_episode

ROOT = Path(__file__).resolve().parent.parent
TINY = [
    "--scenario", "hidden_obstacle", "--algo", "maddpg", "--variant", "plain",
    "--steps", "400", "--num-envs", "2", "--episode-length", "10", "--eval-every", "200",
    "--eval-episodes", "4", "--learning-starts", "100", "--ddpg-batch-size", "16",
    "--ddpg-actor-hidden", "8", "--ddpg-critic-hidden", "8", "--ddpg-update-every", "10",
    "--seeds", "2", "--seed-offset", "7", "--checkpoint-every", "200", "--no-progress",
    "--keep-buffer",
]


def restore_final(folder: Path):
    """The run's spec and its latest checkpoint, restored."""
    spec = train.RunSpec.from_dict(RunFolder(folder).read_config()["run"])
    program = make_train(spec.train)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in spec.seed_list])
    abstract = jax.eval_shape(jax.vmap(program.init), keys)
    checkpoints = Checkpoints(folder / "checkpoints")
    try:
        return spec, checkpoints.restore_latest(abstract.replace(buffer=None), abstract.buffer,
                                              fingerprint(spec.to_dict()))
    finally:
        checkpoints.close()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("commands") / "run"
    assert train.main([*TINY, "--out", str(out)]) == 0
    return out


def test_evaluate_reproduces_the_library_numbers(finished_run, tmp_path, capsys, monkeypatch):
    """``python -m ccrjax.evaluate``'s per-seed numbers are the greedy policy's episode metrics
    computed here from the checkpoint, with the command's documented episode keys."""
    out = tmp_path / "evaluated"
    out.mkdir()
    for name in ("config.json", "checkpoints"):
        source = finished_run / name
        (os.symlink if source.is_dir() else os.link)(source, out / name)
    picture_keys = []
    original_record = evaluate.record_trained_episode

    def record(program, state, key, caption):
        picture_keys.append(np.asarray(jax.random.key_data(key)))
        return original_record(program, state, key, caption=caption)

    monkeypatch.setattr(evaluate, "record_trained_episode", record)
    assert evaluate.main([str(out), "--episodes", "6", "--seed", "5"]) == 0
    capsys.readouterr()
    # The picture's episode comes from --seed (a stream of its own): not training's.
    expected_key = jax.random.fold_in(jax.random.fold_in(
        jax.random.PRNGKey(5), evaluate.EVALUATION_STREAM), evaluate.PICTURE_KEY)
    training_key = jax.random.fold_in(jax.random.PRNGKey(7), evaluate.PICTURE_KEY)
    assert len(picture_keys) == 1
    np.testing.assert_array_equal(picture_keys[0], jax.random.key_data(expected_key))
    assert not np.array_equal(picture_keys[0], jax.random.key_data(training_key))
    assert (out / "episode.png").exists()
    result = json.loads((out / "evaluation.json").read_text())
    spec, restored = restore_final(finished_run)
    assert result["checkpoint_env_steps"] == restored.step == 400
    program = make_train(dataclasses.replace(spec.train, eval_episodes=6))
    keys = jax.random.split(jax.random.PRNGKey(5), len(spec.seed_list))

    @jax.jit
    def greedy_metrics(state, key):
        def act(obs, step_key):
            return program.learner.act(state.learner, obs, step_key, False)

        _, episode = run_episode(program.eval_env, program.transform, state.transform, act,
                                 program.learner.discrete, key)
        return episode_metrics(episode)

    assert result["seeds"] == spec.seed_list == [7, 8]
    for k, seed in enumerate(spec.seed_list):
        state = jax.tree_util.tree_map(lambda x, k=k: x[k], restored.state)
        key = jax.random.fold_in(keys[k], evaluate.EVALUATION_STREAM)
        expected = greedy_metrics(state, key)
        for name in EVAL_METRICS:
            np.testing.assert_allclose(result["per_seed"][str(seed)][name], expected[name],
                                       rtol=1e-5, atol=1e-7, err_msg=f"seed {seed} {name}")
    for name in EVAL_METRICS:
        values = [result["per_seed"][str(s)][name] for s in spec.seed_list]
        expected = mean_ci(values, bounds=METRIC_RANGES[name])
        assert result["mean_ci95"][name] == pytest.approx(expected)
        low, high = METRIC_RANGES[name]
        assert low <= result["mean_ci95"][name]["ci_low"] <= result["mean_ci95"][name]["ci_high"]
        assert result["mean_ci95"][name]["ci_high"] <= high
    # Fresh episodes: not the run's own last evaluation (other keys, other episodes).
    last = [r for r in read_metrics(finished_run / "metrics.csv") if r["env_steps"] == 400]
    assert [r["return"] for r in last] != [result["per_seed"][str(s)]["return"]
                                          for s in spec.seed_list]


def test_a_stopped_and_resumed_run_is_the_uninterrupted_run(finished_run, tmp_path,
                                                            monkeypatch, capsys):
    """Ctrl-C after the first chunk (a real SIGINT to this process), then ``--resume``: the
    final checkpoint holds exactly the uninterrupted run's state (parameters, optimiser
    states, replay buffers, keys, counters), and the metrics are the same."""
    out = tmp_path / "stopped"
    real_update = train.Progress.update
    sent = []

    def update_then_interrupt(self, *args):
        real_update(self, *args)
        if not sent:
            sent.append(True)
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(train.Progress, "update", update_then_interrupt)
    assert train.main([*TINY, "--out", str(out)]) == train.INTERRUPTED
    monkeypatch.setattr(train.Progress, "update", real_update)
    assert "--resume" in capsys.readouterr().err
    assert sorted(int(p.name) for p in (out / "checkpoints").iterdir()) == [200]
    assert train.main(["--out", str(out), "--resume", "--no-progress", "--keep-buffer"]) == 0
    assert "resuming" in capsys.readouterr().err

    _, resumed = restore_final(out)
    _, uninterrupted = restore_final(finished_run)
    assert resumed.step == uninterrupted.step == 400
    assert int(np.min(resumed.state.updates)) > 0  # the resumed chunk trained
    assert resumed.buffer is not None and uninterrupted.buffer is not None  # --keep-buffer
    paths = jax.tree_util.tree_flatten_with_path((uninterrupted.state, uninterrupted.buffer))[0]
    leaves = jax.tree_util.tree_leaves((resumed.state, resumed.buffer))
    assert len(paths) == len(leaves)
    for (path, want), have in zip(paths, leaves, strict=True):
        np.testing.assert_array_equal(np.asarray(have), np.asarray(want),
                                      err_msg=jax.tree_util.keystr(path))
    rows = read_metrics(out / "metrics.csv")
    expected = read_metrics(finished_run / "metrics.csv")
    assert len(rows) == len(expected) == 2 * 3
    for row, want in zip(rows, expected, strict=True):
        assert {k: v for k, v in row.items() if k != "wall_time_s"} == {
            k: v for k, v in want.items() if k != "wall_time_s"}


def run_command(module: str, *args: str, env) -> subprocess.CompletedProcess:
    process = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=300)
    assert process.returncode == 0, process.stderr
    return process


@pytest.mark.slow
def test_sweep_command_at_a_tiny_size(tmp_path, subprocess_env):
    """Two penalties x two seeds of MADDPG, learning once 400 transitions are held (a
    budget of 900 steps and evaluations every 90, rounded to whole iterations of 200
    environment steps: 1,000 and 200, said and recorded); and the refusal of a budget that
    ends before learning starts."""
    out = tmp_path / "sweep"
    refused = subprocess.run(
        [sys.executable, "-m", "ccrjax.sweep", "--steps", "800", "--out", str(out)],
        cwd=ROOT, env=subprocess_env, capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1
    assert "(--steps) 800 ends before learning starts" in refused.stderr
    assert not out.exists()
    process = run_command(
        "ccrjax.sweep", "--variant", "pessimistic", "--scenario", "strong_wind", "--algo",
        "maddpg", "--values", "0", "30", "--seeds", "2", "--steps", "900",
        "--learning-starts", "400", "--eval-episodes", "4", "--out", str(out),
        env=subprocess_env)
    assert "note: --steps 900 runs as 1,000" in process.stderr
    result = json.loads((out / "sweep.json").read_text())
    assert result["parameter"] == "penalty"
    assert [row["value"] for row in result["rows"]] == [0.0, 30.0]
    assert result["env_steps"] == 1000 and result["eval_episodes"] == 4
    assert result["schedule"]["requested"]["total_env_steps"] == 900
    for row in result["rows"]:
        assert row["seeds"] == [100, 101]  # the selection seeds by default
        for name in (*EVAL_METRICS, "cumulative_danger_steps"):
            values = row[name]["per_seed"]
            assert len(values) == 2 and all(np.isfinite(values))
            assert row[name]["mean"] == pytest.approx(np.mean(values))
        for name in ("danger_frequency", "success_rate"):
            assert all(0.0 <= v <= 1.0 for v in row[name]["per_seed"])
        assert all(v < 0 for v in row["return"]["per_seed"])
        assert row["return"]["per_seed"][0] != row["return"]["per_seed"][1]
    table = (out / "sweep.md").read_text()
    assert "| 0 |" in table and "| 30 |" in table
    assert result["nonfinite_iteration"] == [-1, -1, -1, -1]
    assert "Every update of the 4 runs stayed finite." in table
    assert (out / "tradeoff.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow  # the demo's whole pipeline in a process that starts JAX (40 s)
def test_demo_command_at_a_tiny_size(tmp_path, subprocess_env):
    from PIL import Image

    out = tmp_path / "demo"
    process = run_command("ccrjax.demo", "--out", str(out), "--robots", "2", "--steps", "5",
                          env=subprocess_env)
    scenarios = ("turbulence", "strong_wind", "hidden_obstacle", "nominal")
    assert f"wrote {2 * len(scenarios)} pictures" in process.stdout
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{s}.{ext}" for s in scenarios for ext in ("png", "gif"))
    for scenario in scenarios:
        with Image.open(out / f"{scenario}.png") as png:
            assert png.format == "PNG" and min(png.size) > 100
            assert np.unique(np.asarray(png.convert("L"))).size > 10  # a picture, not a blank
        with Image.open(out / f"{scenario}.gif") as gif:
            assert gif.format == "GIF" and gif.n_frames >= 5


def test_sweep_refuses_an_out_it_cannot_or_should_not_write_before_training(tmp_path, capsys,
                                                                             monkeypatch):
    """A file as --out, or a folder that already holds a sweep (without --force), gets one
    line and status 2 before anything compiles; the default values are the protocol's."""
    from experiments import protocol

    def refused(out: Path, *fragments: str) -> None:
        with pytest.raises(SystemExit) as exit_:
            sweep.main(["--steps", "800", "--learning-starts", "400", "--out", str(out)])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        for fragment in fragments:
            assert fragment in err, err

    afile = tmp_path / "afile"
    afile.write_text("")
    refused(afile, "--out", "is a file")
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "sweep.json").write_text("{}")
    refused(earlier, "already holds a sweep", "--force")
    assert (earlier / "sweep.json").read_text() == "{}"
    # A folder of other files (an experiment's results, say) is never written into.
    other = tmp_path / "results"
    other.mkdir()
    (other / "search.json").write_text("{}")
    refused(other, "holds other files than a sweep's")
    assert sorted(p.name for p in other.iterdir()) == ["search.json"]
    with pytest.raises(SystemExit) as exit_:
        sweep.main(["--values", "0", "1", "1", "--steps", "800", "--learning-starts", "400",
                    "--out", str(tmp_path / "repeated")])
    assert exit_.value.code == 2 and "--values repeats 1" in capsys.readouterr().err
    assert not (tmp_path / "repeated").exists()
    assert sweep.DEFAULT_VALUES == {v: values for v, (_, values) in protocol.SEARCHED.items()}


@pytest.mark.slow
def test_the_training_benchmark_times_a_grid_shaped_program(subprocess_env):
    """``benchmarks/train_throughput.py --seeds 2``: two seeds in one program, the rates
    per seed and for both (a smoke test: the benchmark's own numbers are not asserted)."""
    process = subprocess.run(
        [sys.executable, "benchmarks/train_throughput.py", "--algos", "iddpg", "maac",
         "--maac-updates", "1x32", "--iterations", "1", "--repeats", "1", "--seeds", "2",
         "--json"],
        cwd=ROOT, env=subprocess_env, capture_output=True, text=True, timeout=300)
    assert process.returncode == 0, process.stderr
    iddpg, maac = [json.loads(line) for line in process.stdout.splitlines()]
    assert (iddpg["algo"], iddpg["seeds"], iddpg["iterations"]) == ("iddpg", 2, 1)
    assert (maac["algo"], maac["updates"]) == ("maac", "1x32/100")  # the setting asked for
    for row in (iddpg, maac):
        assert row["env_steps_per_s"] > 0
        assert row["env_steps_per_s_all_seeds"] == pytest.approx(2 * row["env_steps_per_s"])


@pytest.mark.slow
def test_the_replay_benchmark_runs_and_both_buffers_restore_exactly(subprocess_env, tmp_path):
    """``benchmarks/replay_compare.py`` (``make bench``'s third) at a small capacity: one row
    per buffer, each holding what was inserted and restored exactly (a smoke test: the
    timings are not asserted)."""
    process = subprocess.run(
        [sys.executable, "benchmarks/replay_compare.py", "--capacity", "20000", "--seeds", "1",
         "--repeats", "1", "--calls", "2", "--tmpdir", str(tmp_path), "--json"],
        cwd=ROOT, env=subprocess_env, capture_output=True, text=True, timeout=300)
    assert process.returncode == 0, process.stderr
    rows = [json.loads(line) for line in process.stdout.splitlines()]
    buffers = {row["buffer"]: row for row in rows[:2]}
    assert list(buffers) == ["ours", "flashbax"] and rows[2]["buffer"] == "flashbax/ours"
    for row in buffers.values():
        assert row["restored_identical"] is True and row["bytes_per_seed"] > 0
        assert "cost" not in row["transition"]  # plain training stores no cost channel


def test_the_training_benchmark_refuses_a_malformed_update_setting_in_one_line(
        subprocess_env):
    """``--maac-updates`` takes updates x batch (``1x256``); anything else is one line and
    status 2, before anything compiles."""
    process = subprocess.run(
        [sys.executable, "benchmarks/train_throughput.py", "--maac-updates", "4x0"],
        cwd=ROOT, env=subprocess_env, capture_output=True, text=True, timeout=120)
    lines = process.stderr.strip().splitlines()
    assert process.returncode == 2 and len(lines) == 1, process.stderr
    assert "--maac-updates" in lines[0] and "1x256" in lines[0]


# A signal whose Python handler runs inside a garbage-collection callback, where an exception
# would be printed as "Exception ignored" and dropped (JAX registers such a callback: a Ctrl-C
# landing there was once lost and the search ran on to exit 0): the stop still happens.
STOP_IN_GC_CALLBACK = """
import gc, signal, sys, time
from ccrjax import terminal

def on_collection(phase, info):
    if phase == "start" and not raised:
        raised.append(True)
        signal.raise_signal(signal.SIGINT)  # handled at the next bytecode: in this callback
        for _ in range(3):
            pass

raised = []

def main():
    gc.callbacks.append(on_collection)
    gc.collect()
    gc.callbacks.remove(on_collection)
    until = time.monotonic() + 10  # work the stop should end within milliseconds
    while time.monotonic() < until:
        pass
    print("ran on", file=sys.stderr)
    return 0

raise SystemExit(terminal.run_command("prog", main, "nothing to keep"))
"""



# A signal that comes while install() is half done: here while it opens the wakeup pipe,
# before any of its handlers is in place (where Python's default handler would raise
# KeyboardInterrupt); install holds the signals until the handlers, the pipe and the
# watcher are all in place.
STOP_DURING_INSTALL = """
import os, signal, sys, time
from ccrjax import terminal

opened = os.pipe

def pipe_after_a_signal():
    os.kill(os.getpid(), signal.SIGINT)
    return opened()

os.pipe = pipe_after_a_signal
terminal.install("prog")
os.pipe = opened
until = time.monotonic() + 10  # work the stop should end within milliseconds
while time.monotonic() < until:
    pass
print("ran on", file=sys.stderr)
"""


@pytest.mark.parametrize("script, last", [
    (STOP_IN_GC_CALLBACK, "prog: stopped by SIGINT; nothing to keep"),
    (STOP_DURING_INSTALL, "prog: stopped by SIGINT; nothing was written"),
], ids=["in-a-gc-callback", "during-install"])
def test_a_signal_where_python_would_drop_or_raise_it_still_stops_the_command_in_one_line(
        script, last, subprocess_env):
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, env=subprocess_env, cwd=ROOT)
    assert done.returncode == terminal.INTERRUPTED, done.stderr
    for sign in ("ran on", "Exception ignored", "Traceback"):
        assert sign not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines()[-1] == last


COMMANDS = sorted(path for folder in ("ccrjax", "experiments")
                  for path in (ROOT / folder).rglob("*.py")
                  if '__name__ == "__main__"' in path.read_text())


@pytest.mark.parametrize("path", COMMANDS, ids=lambda path: str(path.relative_to(ROOT)))
def test_every_command_installs_the_stop_handling_before_its_other_imports(path: Path):
    """A signal is answered from a command's first statement on (``tests/test_stopping.py``
    times its signals from there), so that statement must be the stop handling's, before
    anything slow to import: ``from ccrjax import terminal`` then, as a command,
    ``terminal.install(...)``."""
    body = [node for node in ast.parse(path.read_text()).body
            if not (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant))
            and not (isinstance(node, ast.ImportFrom) and node.module == "__future__")]
    assert ast.unparse(body[0]) == "from ccrjax import terminal", ast.unparse(body[0])
    guard = body[1]
    assert isinstance(guard, ast.If), ast.unparse(guard)
    assert ast.unparse(guard.test) == "__name__ == '__main__'", ast.unparse(guard)
    assert ast.unparse(guard.body[0]).startswith("terminal.install("), ast.unparse(guard)
