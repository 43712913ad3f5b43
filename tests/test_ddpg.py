"""Independent DDPG and MADDPG: critic inputs, targets, soft updates, the update itself."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents.ddpg import DDPG, DDPGConfig
from ccrjax.agents.types import Transition, soft_update

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


def np_mlp(params, x) -> np.ndarray:
    """A ReLU :class:`~ccrjax.agents.networks.MLP` in numpy (one robot's parameters)."""
    layers = params["params"]
    x = np.asarray(x, np.float64)
    for n in range(len(layers)):
        layer = layers[f"Dense_{n}"]
        x = x @ np.asarray(layer["kernel"]) + np.asarray(layer["bias"])
        if n < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def robot(tree, i):
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[i], tree)


def with_distinct_targets(state):
    """Targets that differ from the online networks, so that tests can tell them apart."""
    return state.replace(
        target_actor=jax.tree_util.tree_map(lambda x: x * 1.5, state.actor),
        target_critic=jax.tree_util.tree_map(lambda x: x - 0.1, state.critic),
    )


@pytest.mark.parametrize("algo", ["maddpg", "iddpg"])
def test_td_target_matches_a_hand_computation(learners, algo):
    learner, state = learners[algo]
    state = with_distinct_targets(state)
    batch = batch_of(jax.random.PRNGKey(4))
    target = learner.td_target(state, batch)
    gamma = learner.config.gamma
    # The target actors' next actions, in numpy: tanh of each robot's own network.
    next_actions = np.stack(
        [np.tanh(np_mlp(robot(state.target_actor, j), batch.next_obs[:, j])) for j in range(N)],
        axis=1,
    )
    done = np.asarray(batch.done)
    assert done[0] == 1 and not done[1:].any()
    for i in range(N):
        if algo == "maddpg":
            x = np.concatenate(
                [np.asarray(batch.next_obs).reshape(B, -1), next_actions.reshape(B, -1)], axis=-1
            )
        else:
            x = np.concatenate([batch.next_obs[:, i], next_actions[:, i]], axis=-1)
        q_next = np_mlp(robot(state.target_critic, i), x)[:, 0]
        expected = np.asarray(batch.reward[:, i]) + gamma * (1 - done) * q_next
        np.testing.assert_allclose(target[:, i], expected, rtol=1e-5, atol=1e-6)
        # The bootstrap term is not negligible: a target without it would fail above.
        assert np.min(np.abs(q_next[1:])) > 1e-3


def test_soft_update_is_polyak_averaging():
    target = {"w": jnp.array([1.0, 2.0])}
    online = {"w": jnp.array([3.0, -2.0])}
    out = soft_update(target, online, 0.25)
    np.testing.assert_allclose(out["w"], [1.5, 1.0])


@pytest.mark.parametrize("algo", ["maddpg", "iddpg"])
def test_update_moves_both_targets_by_tau_and_lowers_critic_loss(learners, algo):
    learner, state = learners[algo]
    state = with_distinct_targets(state)
    batch = batch_of(jax.random.PRNGKey(5))
    update = jax.jit(learner.update)
    new_state, metrics = update(state, batch, jax.random.PRNGKey(0))
    tau = learner.config.tau
    for old_target, new_target, old_online, new_online in (
        (state.target_actor, new_state.target_actor, state.actor, new_state.actor),
        (state.target_critic, new_state.target_critic, state.critic, new_state.critic),
    ):
        for t_old, t_new, o_old, o_new in zip(
            jax.tree_util.tree_leaves(old_target),
            jax.tree_util.tree_leaves(new_target),
            jax.tree_util.tree_leaves(old_online),
            jax.tree_util.tree_leaves(new_online),
            strict=True,
        ):
            t_old, t_new = np.asarray(t_old, np.float64), np.asarray(t_new, np.float64)
            expected = (1 - tau) * t_old + tau * np.asarray(o_new, np.float64)
            np.testing.assert_allclose(t_new, expected, rtol=1e-6, atol=1e-7)
            # The online network moved, so the check tells the new online from the old one.
            assert not np.allclose(o_old, o_new, rtol=0, atol=1e-5)
    assert all(np.isfinite(v) for v in jax.tree_util.tree_leaves(metrics))
    # Repeated updates on one batch fit the critic to its (slowly moving) target.
    first_loss = float(metrics["critic_loss"])
    for _ in range(30):
        new_state, metrics = update(new_state, batch, jax.random.PRNGKey(0))
    assert float(metrics["critic_loss"]) < first_loss


@pytest.mark.parametrize("algo", ["maddpg", "iddpg"])
def test_one_actor_step_raises_q_at_the_actors_action(learners, algo):
    """The actor climbs the critic it is trained on (the updated one): every robot's mean
    ``Q_i(o, a_-i, mu_i(o_i))`` is higher under the new actor than under the old."""
    learner, state = learners[algo]
    batch = batch_of(jax.random.PRNGKey(8))
    new_state, _ = jax.jit(learner.update)(state, batch, jax.random.PRNGKey(0))

    @jax.jit
    def q_at_own_action(actor, critic):
        own, _ = learner.policy(actor, batch.obs)
        inputs = learner.critic_input_with_own(batch.obs, batch.action, own)
        return jnp.mean(learner.q_values(critic, inputs), axis=0)  # [N]

    before = np.asarray(q_at_own_action(state.actor, new_state.critic))
    after = np.asarray(q_at_own_action(new_state.actor, new_state.critic))
    assert np.all(after > before + 1e-5), (before, after)


def adam_first_moment(opt_state):
    """Adam's first moment after one step from zero: ``(1 - b1) g`` (b1 = 0.9)."""
    (adam, _) = opt_state
    return jax.tree_util.tree_map(lambda m: np.asarray(m, np.float64) / 0.1, adam.mu)


def clipped_by_hand(grads, max_norm):
    """Each robot's gradient of each variable scaled to norm ``max_norm`` if it is longer."""

    def clip(g):
        g = np.asarray(g, np.float64)
        norm = np.sqrt(np.sum(g.reshape(g.shape[0], -1) ** 2, axis=1))
        scale = np.minimum(1.0, max_norm / norm)
        return g * scale.reshape((-1,) + (1,) * (g.ndim - 1)), norm

    return jax.tree_util.tree_map(clip, grads)


@pytest.mark.parametrize("algo", ["maddpg", "iddpg"])
def test_huge_gradients_are_clipped_per_robot_and_variable(learners, algo):
    """Rewards of 1e6 and a critic scaled up make every gradient far longer than 0.5; the
    gradient each optimiser received (Adam's first moment) is the hand-computed gradient
    clipped to norm 0.5 per robot and variable (the original MADDPG's ``clip_by_norm``).
    One Adam step from zero is scale-free, so the first moment is where clipping shows."""
    learner, state = learners[algo]
    clip = learner.config.grad_clip
    assert clip == 0.5
    state = state.replace(critic=jax.tree_util.tree_map(lambda x: 100.0 * x, state.critic))
    state = state.replace(target_critic=state.critic,
                          critic_opt=learner.critic_optimiser.init(state.critic))
    batch = batch_of(jax.random.PRNGKey(9))
    batch = batch.replace(reward=batch.reward * 1e6)
    new_state, _ = jax.jit(learner.update)(state, batch, jax.random.PRNGKey(0))
    config = learner.config

    @jax.jit
    def critic_grads(params):
        target = learner.td_target(state, batch)
        inputs = learner.critic_input(batch.obs, batch.action)

        def loss(params):
            q = learner.q_values(params, inputs)
            return jnp.sum(jnp.mean((q - target) ** 2, axis=0))

        return jax.grad(loss)(params)

    @jax.jit
    def actor_grads(params, critic):
        def loss(params):
            pre = jax.vmap(learner.actor.apply, in_axes=(0, 1), out_axes=1)(params, batch.obs)
            inputs = learner.critic_input_with_own(batch.obs, batch.action, jnp.tanh(pre))
            q = learner.q_values(critic, inputs)
            return jnp.sum(-jnp.mean(q, axis=0)) + config.actor_regulariser * jnp.sum(
                jnp.mean(pre**2, axis=(0, 2))
            )

        return jax.grad(loss)(params)

    for received, grads in (
        (new_state.critic_opt, critic_grads(state.critic)),
        # The actor's loss goes through the critic updated in the same step.
        (new_state.actor_opt, actor_grads(state.actor, new_state.critic)),
    ):
        expected = clipped_by_hand(grads, clip)
        got = adam_first_moment(received)
        flat_expected = jax.tree_util.tree_leaves(expected, is_leaf=lambda x: isinstance(x, tuple))
        for (want, norm), have in zip(flat_expected, jax.tree_util.tree_leaves(got), strict=True):
            assert np.all(norm > 4 * clip), norm  # every gradient is clipped ...
            np.testing.assert_allclose(have, want, rtol=2e-3, atol=1e-6)  # ... to this
            have_norm = np.sqrt(np.sum(have.reshape(N, -1) ** 2, axis=1))
            np.testing.assert_allclose(have_norm, clip, rtol=2e-3)


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
