"""The extension points (ccrjax.registry): a transform and a scenario defined outside the
package register and train through make_train and through ``python -m ccrjax.train
--plugin``. The transform is the README's worked example, run as the README prints it."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax import cli, registry, train
from ccrjax.agents.ddpg import DDPG, DDPGConfig
from ccrjax.envs.scenarios import SCENARIOS
from ccrjax.training import TrainConfig, config_from_dict, config_to_dict, make_train

ROOT = Path(__file__).resolve().parents[1]
SCENARIO_PLUGIN = ROOT / "tests" / "plugins" / "dead_zone.py"
TINY = dict(num_robots=3, num_envs=2, total_env_steps=150, learning_starts=50, eval_every=50,
            eval_episodes=2)


def readme_example() -> str:
    """The README's Python block that registers a transform."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    [block] = [b for b in blocks if "register_transform(" in b]
    return block


@pytest.fixture(scope="module", autouse=True)
def registries_restored() -> Iterator[None]:
    """The registries as they were once this file's tests are done: other test files in
    the same worker see only the built-in methods."""
    tables = (registry._TRANSFORMS, registry._LEARNERS, SCENARIOS)
    saved = [dict(table) for table in tables]
    yield
    for table, before in zip(tables, saved, strict=True):
        table.clear()
        table.update(before)


@pytest.fixture(scope="module")
def plugins(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """The README's transform saved as crowding.py and the test scenario, both loaded."""
    path = tmp_path_factory.mktemp("plugin") / "crowding.py"
    path.write_text(readme_example())
    names = [str(path), str(SCENARIO_PLUGIN)]
    cli.load_plugins([word for name in names for word in ("--plugin", name)])
    return names


def test_registered_names_join_the_registry_and_round_trip(plugins: list[str]) -> None:
    assert "crowding" in registry.transform_names()
    assert "dead_zone" in registry.scenario_names()
    crowding = registry.transform_entry("crowding").type
    config = TrainConfig(scenario="dead_zone", variant="crowding",
                         transform=crowding(weight=0.5), **TINY)
    assert config_from_dict(json.loads(json.dumps(config_to_dict(config)))) == config
    with pytest.raises(ValueError, match="Crowding.radius must be > 0"):
        crowding(radius=0.0)
    cli.load_plugins(["--plugin", plugins[0]])  # loaded again: registers again quietly


def test_a_plugin_transform_trains_through_make_train_vmapped_over_its_params(
        plugins: list[str]) -> None:
    """Weight 0 is the plain learner (to float rounding: a vmapped program need not round
    as the single one does); a large weight changes what is learnt."""
    keys = jnp.stack([jax.random.PRNGKey(3)] * 2)
    crowding = make_train(TrainConfig(scenario="dead_zone", variant="crowding", **TINY))
    _, history = jax.jit(jax.vmap(crowding.train))(keys, {"weight": jnp.array([0.0, 50.0])})
    _, plain = jax.jit(make_train(TrainConfig(scenario="dead_zone", variant="plain",
                                              **TINY)).train)(keys[0])
    for name in ("return", "danger_frequency", "target_distance"):
        np.testing.assert_allclose(history[name][0], plain[name], rtol=1e-5, atol=1e-6,
                                   err_msg=name)
    assert not np.array_equal(history["target_distance"][1], plain["target_distance"])


def test_unknown_and_clashing_registrations_are_refused() -> None:
    with pytest.raises(ValueError, match="variant must be one of"):
        TrainConfig(variant="no_such_method")
    with pytest.raises(ValueError, match="already registered"):
        registry.register_transform("plain", dataclasses.make_dataclass("Other", []))
    with pytest.raises(ValueError, match="must be an identifier"):
        registry.register_learner("my-learner", DDPGConfig, DDPG, default_budget=1000)
    with pytest.raises(ValueError, match="default_budget"):
        registry.register_learner("mine", DDPGConfig, DDPG, default_budget=0)


def test_a_registered_learner_trains_under_its_own_name() -> None:
    registry.register_learner("maddpg_small", DDPGConfig, DDPG, default_budget=150,
                              configure=lambda c: dataclasses.replace(
                                  c, centralised_critic=True, actor_hidden=(16, 16)),
                              replace=True)
    config = TrainConfig(algo="maddpg_small", **{**TINY, "total_env_steps": None})
    assert config.budget == 150 and config.resolved_learner.actor_hidden == (16, 16)
    _, history = jax.jit(make_train(config).train)(jax.random.PRNGKey(0))
    assert np.isfinite(history["return"]).all()


@pytest.mark.slow
def test_the_command_trains_plugins_and_refuses_their_bad_options(
        plugins: list[str], tmp_path: Path) -> None:
    base = [sys.executable, "-m", "ccrjax.train", "--plugin", plugins[0], "--plugin",
            plugins[1], "--scenario", "dead_zone", "--variant", "crowding"]
    tiny = ["--robots", "3", "--num-envs", "2", "--steps", "150", "--learning-starts", "50",
            "--eval-every", "50", "--eval-episodes", "2", "--no-progress"]
    bad = subprocess.run([*base, "--crowding-radius", "-1", "--out", str(tmp_path / "bad")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr.strip().splitlines() == [
        "python -m ccrjax.train: error: --crowding-radius must be > 0, got -1.0"]
    out = tmp_path / "run"
    done = subprocess.run([*base, "--crowding-weight", "0.5", *tiny, "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    run = json.loads((out / "config.json").read_text())["run"]["train"]
    assert (run["scenario"], run["variant"], run["transform"]) == (
        "dead_zone", "crowding", {"weight": 0.5, "radius": 0.3})
    assert (out / "policy").is_dir() and (out / "episode.png").exists()


def test_a_plugin_transform_option_is_refused_for_another_variant(
        plugins: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        train.main(["--plugin", plugins[0], "--variant", "plain", "--crowding-weight", "1"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "python -m ccrjax.train: error: --crowding-* options apply to --variant crowding, "
        "not plain")
