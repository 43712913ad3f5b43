"""``ccrjax.load_team``: a CCR run's exported team acts in whole episodes, its transform
(CCR's fitted model, the shared scores) included, exactly as the run's evaluation does."""

from __future__ import annotations

import dataclasses
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ccrjax
from ccrjax.run.policy import TRANSFORM_STATE, export_policy
from ccrjax.run.spec import RunSpec
from ccrjax.training import TrainConfig, make_train


@pytest.mark.slow  # trains a CCR team and compiles its episodes (50 s)
def test_a_ccr_team_runs_its_episodes_with_its_own_model(tmp_path):
    """Export a CCR team (two seeds, the second one's model statistics made unlike the
    first's) and load it back from the export and config alone: its episode and metrics
    equal the program's evaluation of the same state, seed by seed, and they depend on the
    transform state (the model), which a policy export without it cannot give."""
    config = TrainConfig(scenario="turbulence", algo="iddpg", variant="ccr", num_robots=3,
                         num_envs=2, episode_length=6, eval_episodes=3,
                         total_env_steps=120, eval_every=60, learning_starts=12)
    spec = RunSpec(train=config, seeds=2, seed_offset=5)
    program = make_train(config)
    state = jax.vmap(program.init)(jnp.stack([jax.random.PRNGKey(s) for s in spec.seed_list]))
    stats = state.transform.statistics  # a model fitted on made-up data for the second seed
    features = jax.random.normal(jax.random.PRNGKey(9), (64, stats.feature_moment.shape[-1]))
    targets = jax.random.normal(jax.random.PRNGKey(10), (64, stats.target_moment.shape[-1]))
    stats = stats.replace(
        feature_moment=stats.feature_moment.at[1].set(features.T @ features / 64),
        target_moment=stats.target_moment.at[1].set(features.T @ targets / 64),
        total_weight=stats.total_weight.at[1].set(64.0))
    state = state.replace(transform=state.transform.replace(statistics=stats))
    (tmp_path / "config.json").write_text(json.dumps({"run": spec.to_dict()}))
    export_policy(tmp_path, program, state.learner, spec.seed_list, state.transform)
    assert (tmp_path / "policy" / TRANSFORM_STATE).is_dir()
    key = jax.random.PRNGKey(3)
    teams = []
    for index, seed in enumerate(spec.seed_list):
        team = ccrjax.load_team(tmp_path, seed=seed)
        one = jax.tree_util.tree_map(lambda x, i=index: x[i], state)
        expected = program.evaluate(one, key)
        got = team.evaluate(key)
        for name, value in expected.items():
            np.testing.assert_allclose(np.asarray(got[name]), np.asarray(value), rtol=1e-5,
                                       atol=1e-6, err_msg=name)
        episode = team.episode(key)
        assert episode.position.shape == (config.episode_length + 1, 3, 2, 3)
        assert set(episode.info) >= {"emergency_score", "intrinsic_reward"}  # CCR's
        teams.append((team, episode))
    # The second seed's own model scores its team otherwise than the first seed's would.
    (first, _), (second, episode) = teams
    swapped = dataclasses.replace(second, transform_state=first.transform_state).episode(key)
    assert not np.allclose(np.asarray(swapped.info["emergency_score"]),
                           np.asarray(episode.info["emergency_score"]))
    with pytest.raises(ValueError, match="seed must be one of"):
        ccrjax.load_team(tmp_path, seed=0)
    shutil.rmtree(tmp_path / "policy" / TRANSFORM_STATE)  # an export from before it was kept
    with pytest.raises(FileNotFoundError, match="holds no transform state.*ccrjax.evaluate"):
        ccrjax.load_team(tmp_path, seed=5)
