"""The README's Python examples run as printed (the extension example runs in
tests/test_registry.py): training five seeds and five lambdas, then loading a run."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)


@pytest.mark.slow
def test_the_readme_api_examples_run_as_printed(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    training, loading = [b for b in readme_blocks() if "register_transform(" not in b]
    assert "make_train" in training and "load_team" in loading
    run = tmp_path / "runs" / "my-run"
    made = subprocess.run(
        [sys.executable, "-m", "ccrjax.train", "--variant", "ccr", "--robots", "3",
         "--num-envs", "2", "--steps", "150", "--learning-starts", "50", "--eval-every", "50",
         "--eval-episodes", "2", "--no-progress", "--out", str(run)],
        capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert made.returncode == 0, made.stderr[-2000:]
    monkeypatch.chdir(tmp_path)
    names: dict = {}
    exec(compile(training, "README.md", "exec"), names)
    history = names["history"]
    assert np.asarray(history["env_steps"]).shape[0] == 5
    assert np.isfinite(np.asarray(history["return"])).all()
    exec(compile(loading, "README.md", "exec"), names)
    assert 0.0 <= float(names["metrics"]["success_rate"]) <= 1.0
