"""Independent DDPG and MADDPG: critic inputs, targets, soft updates, the update itself."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.learners.base import Transition, soft_update
from ccrjax.learners.ddpg import DDPG, DDPGConfig

N, F, B = 3, 7, 16
SMALL = DDPGConfig(actor_hidden=(8,), critic_hidden=(8,), batch_size=B)


def batch_of(key: jax.Array) -> Transition:
    keys = jax.random.split(key, 4)
    return Transition(
        obs=jax.random.normal(keys[0], (B, N, F)),
        action=jax.random.uniform(keys[1], (B, N, 2), minval=-1, maxval=1),
        reward=jax.random.normal(keys[2], (B, N)),
        next_obs=jax.random.normal(keys[3], (B, N, F)),
        done=jnp.zeros((B,)).at[0].set(1.0),
    )


@pytest.fixture(scope="module")
def learners():
    maddpg = DDPG(dataclasses.replace(SMALL, centralised_critic=True))
    iddpg = DDPG(dataclasses.replace(SMALL, centralised_critic=False))
    key = jax.random.PRNGKey(0)
    return {
        "maddpg": (maddpg, maddpg.init(key, N, F)),
        "iddpg": (iddpg, iddpg.init(key, N, F)),
    }


def test_names_and_critic_sizes(learners):
    maddpg, _ = learners["maddpg"]
    iddpg, _ = learners["iddpg"]
    assert (maddpg.name, iddpg.name) == ("maddpg", "iddpg")
    assert maddpg.critic_input_size(N, F) == N * (F + 2)
    assert iddpg.critic_input_size(N, F) == F + 2


def test_independent_critic_sees_only_its_own_observation_and_action(learners):
    iddpg, _ = learners["iddpg"]
    batch = batch_of(jax.random.PRNGKey(1))
    inputs = iddpg.critic_input(batch.obs, batch.action)
    assert inputs.shape == (B, N, F + 2)
    for i in range(N):
        expected = np.concatenate([batch.obs[:, i], batch.action[:, i]], axis=-1)
        np.testing.assert_array_equal(inputs[:, i], expected)


def test_centralised_critic_sees_every_observation_and_action(learners):
    maddpg, _ = learners["maddpg"]
    batch = batch_of(jax.random.PRNGKey(2))
    inputs = maddpg.critic_input(batch.obs, batch.action)
    joint = np.concatenate(
        [np.asarray(batch.obs).reshape(B, -1), np.asarray(batch.action).reshape(B, -1)], axis=-1
    )
    for i in range(N):
        np.testing.assert_array_equal(inputs[:, i], joint)


def test_actor_loss_input_replaces_only_the_robots_own_action(learners):
    maddpg, _ = learners["maddpg"]
    batch = batch_of(jax.random.PRNGKey(3))
    own = jnp.full((B, N, 2), 0.5)
    inputs = maddpg.critic_input_with_own(batch.obs, batch.action, own)
    for i in range(N):
        actions = np.array(batch.action)
        actions[:, i] = 0.5
        expected = np.concatenate(
            [np.asarray(batch.obs).reshape(B, -1), actions.reshape(B, -1)], axis=-1
        )
        np.testing.assert_array_equal(inputs[:, i], expected)


@pytest.mark.parametrize("algo", ["maddpg", "iddpg"])
def test_td_target_matches_a_hand_computation(learners, algo):
    learner, state = learners[algo]
    state = state.replace(
        target_actor=jax.tree_util.tree_map(lambda x: x * 1.5, state.actor),
        target_critic=jax.tree_util.tree_map(lambda x: x - 0.1, state.critic),
    )
    batch = batch_of(jax.random.PRNGKey(4))
    target = learner.td_target(state, batch)
    gamma = learner.config.gamma
    for i in range(N):
        actor_i = jax.tree_util.tree_map(lambda x, i=i: x[i], state.target_actor)
        critic_i = jax.tree_util.tree_map(lambda x, i=i: x[i], state.target_critic)
        next_actions = np.stack(
            [
                np.tanh(
                    learner.actor.apply(
                        jax.tree_util.tree_map(lambda x, j=j: x[j], state.target_actor),
                        batch.next_obs[:, j],
                    )
                )
                for j in range(N)
            ],
            axis=1,
        )
        np.testing.assert_allclose(
            next_actions[:, i], np.tanh(learner.actor.apply(actor_i, batch.next_obs[:, i])),
            rtol=1e-6,
        )
        if algo == "maddpg":
            x = np.concatenate(
                [np.asarray(batch.next_obs).reshape(B, -1), next_actions.reshape(B, -1)], axis=-1
            )
        else:
            x = np.concatenate([batch.next_obs[:, i], next_actions[:, i]], axis=-1)
        q_next = np.asarray(learner.critic.apply(critic_i, x))[:, 0]
        expected = np.asarray(batch.reward[:, i]) + gamma * (1 - np.asarray(batch.done)) * q_next
        np.testing.assert_allclose(target[:, i], expected, rtol=1e-5, atol=1e-5)


def test_soft_update_is_polyak_averaging():
    target = {"w": jnp.array([1.0, 2.0])}
    online = {"w": jnp.array([3.0, -2.0])}
    out = soft_update(target, online, 0.25)
    np.testing.assert_allclose(out["w"], [1.5, 1.0])


@pytest.mark.parametrize("algo", ["maddpg", "iddpg"])
def test_update_moves_targets_by_tau_and_lowers_critic_loss(learners, algo):
    learner, state = learners[algo]
    batch = batch_of(jax.random.PRNGKey(5))
    update = jax.jit(learner.update)
    new_state, metrics = update(state, batch, jax.random.PRNGKey(0))
    tau = learner.config.tau
    for t_old, t_new, online in zip(
        jax.tree_util.tree_leaves(state.target_critic),
        jax.tree_util.tree_leaves(new_state.target_critic),
        jax.tree_util.tree_leaves(new_state.critic),
        strict=True,
    ):
        np.testing.assert_allclose(t_new, (1 - tau) * t_old + tau * online, rtol=1e-6, atol=1e-7)
    assert all(np.isfinite(v) for v in jax.tree_util.tree_leaves(metrics))
    # Repeated updates on one batch fit the critic to its (slowly moving) target.
    first_loss = float(metrics["critic_loss"])
    for _ in range(30):
        new_state, metrics = update(new_state, batch, jax.random.PRNGKey(0))
    assert float(metrics["critic_loss"]) < first_loss


def test_robots_learn_independently(learners):
    """Robot 0's reward does not move robot 1's critic (parameters are per robot)."""
    learner, state = learners["maddpg"]
    batch = batch_of(jax.random.PRNGKey(6))
    changed = batch.replace(reward=batch.reward.at[:, 0].add(10.0))
    a, _ = learner.update(state, batch, jax.random.PRNGKey(0))
    b, _ = learner.update(state, changed, jax.random.PRNGKey(0))
    for leaf_a, leaf_b in zip(
        jax.tree_util.tree_leaves(a.critic), jax.tree_util.tree_leaves(b.critic), strict=True
    ):
        assert not np.allclose(leaf_a[0], leaf_b[0])
        np.testing.assert_array_equal(leaf_a[1:], leaf_b[1:])


def test_act_explores_only_when_asked_and_stays_in_bounds(learners):
    learner, state = learners["maddpg"]
    obs = jax.random.normal(jax.random.PRNGKey(7), (B, N, F)) * 10
    greedy = learner.act(state, obs, jax.random.PRNGKey(0), False)
    greedy_jit = jax.jit(learner.act, static_argnums=3)(state, obs, jax.random.PRNGKey(1), False)
    np.testing.assert_allclose(greedy, greedy_jit, rtol=1e-6, atol=1e-6)
    noisy = learner.act(state, obs, jax.random.PRNGKey(0), True)
    assert not np.allclose(greedy, noisy)
    assert np.all(np.abs(noisy) <= 1.0)


@pytest.mark.parametrize(
    "field, value",
    [
        ("actor_lr", -1e-3),
        ("critic_lr", float("nan")),
        ("batch_size", 0),
        ("actor_hidden", ()),
        ("gamma", 1.0),
        ("tau", 0.0),
        ("exploration_noise", float("inf")),
    ],
)
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"DDPGConfig.{field}"):
        DDPGConfig(**{field: value})


def test_flops_count_is_about_one_gigaflop_for_the_reference_size():
    learner = DDPG(DDPGConfig())
    flops = learner.flops_per_update(5, 23)
    assert 0.8e9 < flops < 1.3e9
