"""MAAC: the attention critic, the baseline, targets, the update, and a short learning run."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents.maac import MAAC, MAACConfig
from ccrjax.agents.maac_parts import attend, attention_logit_penalty, baseline, sample_actions
from ccrjax.agents.types import Transition
from ccrjax.envs.env import EmergencyEnv
from ccrjax.training import TrainConfig, make_train

N, F, B = 3, 6, 8
HEADS = 2
SMALL = MAACConfig(
    policy_hidden=(8, 8), critic_hidden=8, attention_heads=HEADS, batch_size=B, tau=0.1
)
A = SMALL.num_actions  # box9's 9


def robot(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def leaky(x):
    return np.where(x > 0, x, 0.01 * x)


def np_mlp(params, x) -> np.ndarray:
    """A :class:`~ccrjax.agents.networks.MLP` with leaky ReLU, in numpy (one robot)."""
    layers = params["params"]
    x = np.asarray(x, np.float64)
    for n in range(len(layers)):
        layer = layers[f"Dense_{n}"]
        x = x @ np.asarray(layer["kernel"]) + np.asarray(layer["bias"])
        if n < len(layers) - 1:
            x = leaky(x)
    return x


def batch_of(seed: int) -> Transition:
    """A random batch in numpy (eager JAX ops would each compile a small program)."""
    rng = np.random.default_rng(seed)
    done = np.zeros((B,), np.float32)
    done[0] = 1.0
    return Transition(
        obs=rng.normal(size=(B, N, F)).astype(np.float32),
        action=rng.integers(0, A, (B, N)).astype(np.int32),
        reward=rng.normal(size=(B, N)).astype(np.float32),
        next_obs=rng.normal(size=(B, N, F)).astype(np.float32),
        done=done,
    )


def reference_q(learner: MAAC, params, obs, action) -> np.ndarray:
    """The attention critic written out robot by robot, head by head, without masks:
    robot ``i`` attends over the list of the other robots. Returns ``[B, N, 5]``."""
    obs = np.asarray(obs, np.float64)
    onehot = np.eye(A)[np.asarray(action)]
    att = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), params["attention"])
    d = learner.config.critic_hidden // HEADS
    e, s = [], []
    for j in range(N):
        enc = robot(params["encoder"], j)["params"]
        st = robot(params["state_encoder"], j)["params"]
        inp = np.concatenate([obs[:, j], onehot[:, j]], axis=-1)
        e.append(leaky(inp @ np.asarray(enc["kernel"]) + np.asarray(enc["bias"])))
        s.append(leaky(obs[:, j] @ np.asarray(st["kernel"]) + np.asarray(st["bias"])))
    out = []
    for i in range(N):
        others = [j for j in range(N) if j != i]
        heads = []
        for h in range(HEADS):
            cols = slice(h * d, (h + 1) * d)
            query = s[i] @ att["query"][:, cols]
            logits = np.stack(
                [np.sum(query * (e[j] @ att["key"][:, cols]), axis=-1) for j in others], axis=1
            ) / math.sqrt(d)
            weights = np.exp(logits - logits.max(axis=1, keepdims=True))
            weights /= weights.sum(axis=1, keepdims=True)
            values = [
                leaky(e[j] @ att["value"][:, cols] + att["value_bias"][cols]) for j in others
            ]
            heads.append(sum(weights[:, k : k + 1] * values[k] for k in range(len(others))))
        head_in = np.concatenate([s[i], *heads], axis=-1)
        out.append(np_mlp(robot(params["head"], i), head_in))
    return np.stack(out, axis=1)


class Jitted:
    """The learner's functions compiled once for the tests' shapes (eager calls of small
    flax networks compile op by op, which is slower than one compilation)."""

    def __init__(self, learner: MAAC) -> None:
        self.critic_values = jax.jit(learner.critic_values)
        self.td_target = jax.jit(learner.td_target)
        self.attend = jax.jit(attend, static_argnums=3)
        self.update = jax.jit(learner.update)


@pytest.fixture(scope="module")
def setup():
    learner = MAAC(SMALL)
    learner.jit = Jitted(learner)
    state = jax.jit(learner.init, static_argnums=(1, 2))(jax.random.PRNGKey(0), N, F)
    state = jax.tree_util.tree_map(np.asarray, state)
    # Targets different from the online networks, so that tests can tell them apart.
    state = state.replace(
        target_policy=jax.tree_util.tree_map(lambda x: 1.5 * np.asarray(x), state.policy),
        target_critic=jax.tree_util.tree_map(lambda x: 0.8 * np.asarray(x) + 0.01, state.critic),
    )
    return learner, state


def test_attention_weights_exclude_the_robot_itself(setup):
    learner, state = setup
    rng = np.random.default_rng(1)
    e = rng.normal(size=(B, N, SMALL.critic_hidden)).astype(np.float32)
    s = rng.normal(size=(B, N, SMALL.critic_hidden)).astype(np.float32)
    att = state.critic["attention"]
    x, weights, _ = learner.jit.attend(att, e, s, HEADS)
    assert weights.shape == (B, N, N, HEADS)
    for i in range(N):
        assert np.all(np.asarray(weights[:, i, i]) == 0.0)
    np.testing.assert_allclose(np.sum(weights, axis=2), 1.0, rtol=1e-6)
    for i in range(N):
        changed = e.copy()
        changed[:, i] += 3.0
        x_changed, _, _ = learner.jit.attend(att, changed, s, HEADS)
        np.testing.assert_array_equal(x_changed[:, i], x[:, i])
        for k in range(N):
            if k != i:
                assert not np.allclose(x_changed[:, k], x[:, k])


def test_robot_i_q_vector_does_not_depend_on_its_own_action(setup):
    learner, state = setup
    batch = batch_of(2)
    all_q, _, _ = learner.jit.critic_values(state.critic, batch.obs, batch.action)
    for i in range(N):
        changed = batch.action.copy()
        changed[:, i] = (changed[:, i] + 1) % A
        all_q_changed, _, _ = learner.jit.critic_values(state.critic, batch.obs, changed)
        np.testing.assert_allclose(all_q_changed[:, i], all_q[:, i], rtol=1e-6, atol=1e-6)
        assert not np.allclose(all_q_changed[:, (i + 1) % N], all_q[:, (i + 1) % N])


def test_critic_matches_a_robot_by_robot_reference(setup):
    learner, state = setup
    batch = batch_of(3)
    all_q, _, logits = learner.jit.critic_values(state.critic, batch.obs, batch.action)
    expected = reference_q(learner, state.critic, batch.obs, batch.action)
    np.testing.assert_allclose(all_q, expected, rtol=1e-4, atol=1e-5)
    # The regulariser: per robot, sum over heads of the mean squared logit over j != i.
    penalty = attention_logit_penalty(logits)
    for i in range(N):
        others = [j for j in range(N) if j != i]
        want = sum(np.mean(np.asarray(logits)[:, i, others, h] ** 2) for h in range(HEADS))
        np.testing.assert_allclose(penalty[i], want, rtol=1e-5)


def test_baseline_is_the_policy_weighted_sum_of_q_values(setup):
    learner, state = setup
    batch = batch_of(4)
    logits = np.stack([np_mlp(robot(state.policy, i), batch.obs[:, i]) for i in range(N)], 1)
    probs = np.exp(logits) / np.sum(np.exp(logits), axis=-1, keepdims=True)
    all_q, _, _ = learner.jit.critic_values(state.critic, batch.obs, batch.action)
    got = baseline(all_q, probs)
    for i in range(N):
        expected = np.zeros(B)
        for a in range(A):
            # Q_i(o, (a, a_-i)): the critic called with robot i's action replaced by a.
            replaced = np.array(batch.action)
            replaced[:, i] = a
            all_q_a, _, _ = learner.jit.critic_values(state.critic, batch.obs, replaced)
            q = np.take_along_axis(np.asarray(all_q_a), replaced[..., None], axis=-1)[:, i, 0]
            expected += probs[:, i, a] * q
        np.testing.assert_allclose(got[:, i], expected, rtol=1e-5, atol=1e-6)


def test_td_target_matches_a_hand_computation(setup):
    learner, state = setup
    batch = batch_of(5)
    gumbel = np.random.default_rng(6).gumbel(size=(B, N, A)).astype(np.float32)
    target = learner.jit.td_target(state, batch, gumbel)
    logits = np.stack(
        [np_mlp(robot(state.target_policy, j), batch.next_obs[:, j]) for j in range(N)], axis=1
    )
    # The Gumbel-max trick: argmax(logits + Gumbel noise) is a sample of softmax(logits).
    next_action = np.argmax(logits + gumbel, axis=-1)
    log_probs = logits - np.log(np.sum(np.exp(logits), axis=-1, keepdims=True))
    log_pi = np.take_along_axis(log_probs, next_action[..., None], axis=-1)[..., 0]
    all_q = reference_q(learner, state.target_critic, batch.next_obs, next_action)
    next_q = np.take_along_axis(all_q, next_action[..., None], axis=-1)[..., 0]
    c = learner.config
    expected = (
        np.asarray(batch.reward)
        + c.gamma * (1 - np.asarray(batch.done))[:, None] * next_q
        - log_pi / c.reward_scale
    )
    np.testing.assert_allclose(target, expected, rtol=1e-4, atol=1e-5)


def test_normalise_rewards_per_robot(setup):
    learner, _ = setup
    assert learner.needs_reward_stats
    batch = batch_of(7)
    mean = np.array([1.0, -2.0, 0.5], np.float32)
    std = np.array([2.0, 0.5, 1.0], np.float32)
    out = learner.normalise_rewards(batch, mean, std)
    np.testing.assert_allclose(out.reward, (batch.reward - mean) / std, rtol=1e-6)
    assert not MAAC(dataclasses.replace(SMALL, normalise_rewards=False)).needs_reward_stats


def test_shared_critic_gradients_are_divided_by_the_number_of_robots(setup):
    learner, state = setup
    ones = jax.tree_util.tree_map(np.ones_like, state.critic)
    scaled = learner.scale_shared_grads(ones, N)
    for name, value in scaled.items():
        want = 1.0 / N if name in ("attention", "encoder") else 1.0
        for leaf in jax.tree_util.tree_leaves(value):
            np.testing.assert_allclose(leaf, want)


def test_update_changes_everything_finitely_and_moves_targets_by_tau(setup):
    learner, state = setup
    batch = batch_of(8)
    new_state, metrics = learner.jit.update(state, batch, jax.random.PRNGKey(9))
    assert all(np.isfinite(float(v)) for v in metrics.values())
    for old, new in (
        (state.critic, new_state.critic),
        (state.policy, new_state.policy),
    ):
        leaves = zip(jax.tree_util.tree_leaves(old), jax.tree_util.tree_leaves(new), strict=True)
        for a, b in leaves:
            assert np.all(np.isfinite(b))
            assert not np.allclose(a, b)
    tau = learner.config.tau
    for target_old, target_new, online in (
        (state.target_critic, new_state.target_critic, new_state.critic),
        (state.target_policy, new_state.target_policy, new_state.policy),
    ):
        for t_old, t_new, o in zip(
            jax.tree_util.tree_leaves(target_old),
            jax.tree_util.tree_leaves(target_new),
            jax.tree_util.tree_leaves(online),
            strict=True,
        ):
            np.testing.assert_allclose(t_new, (1 - tau) * t_old + tau * o, rtol=1e-5, atol=1e-7)
    # Repeated updates on one batch (same compiled update) fit the critic.
    update = learner.jit.update
    first_loss = float(metrics["critic_loss"])
    for _ in range(30):
        new_state, metrics = update(new_state, batch, jax.random.PRNGKey(9))
    assert float(metrics["critic_loss"]) < first_loss


def test_one_policy_step_moves_probability_towards_the_positive_advantage(setup):
    """A critic whose Q is ``good_q`` for action 2 and 0 for every other action, whatever
    the observation: action 2 has advantage ``good_q (1 - pi(2)) > 0``, the others
    ``-good_q pi(2) < 0``. One update raises every robot's mean probability of action 2."""
    learner, state = setup
    good, good_q = 2, 5.0
    head = jax.tree_util.tree_map(np.array, state.critic["head"])
    last = head["params"]["Dense_1"]
    last["kernel"][:] = 0.0
    last["bias"][:] = 0.0
    last["bias"][:, good] = good_q
    critic = {**state.critic, "head": head}
    state = state.replace(critic=critic, target_critic=critic,
                          critic_opt=learner.critic_optimiser.init(critic))
    rng = np.random.default_rng(13)
    batch = Transition(
        obs=rng.normal(size=(64, N, F)).astype(np.float32),
        action=rng.integers(0, A, (64, N)).astype(np.int32),
        reward=np.zeros((64, N), np.float32),
        next_obs=rng.normal(size=(64, N, F)).astype(np.float32),
        done=np.zeros((64,), np.float32),
    )
    new_state, _ = learner.jit.update(state, batch, jax.random.PRNGKey(14))
    # The updated critic (the one the policy step used) still ranks action 2 first.
    all_q, _, _ = learner.jit.critic_values(new_state.critic, batch.obs, batch.action)
    assert np.all(np.argmax(np.asarray(all_q), axis=-1) == good)

    def probability_of_good(policy):
        logits = np.stack([np_mlp(robot(policy, i), batch.obs[:, i]) for i in range(N)], 1)
        probs = np.exp(logits - logits.max(-1, keepdims=True))
        return np.mean(probs[..., good] / probs.sum(-1), axis=0)  # [N]

    before = probability_of_good(state.policy)
    after = probability_of_good(new_state.policy)
    assert np.all(after > before * 1.004), (before, after)  # a relative rise of 0.4%


class RewardSpy(MAAC):
    """MAAC reporting the rewards of the batches its update receives (as metrics)."""

    def update(self, state, batch, key):
        state, metrics = super().update(state, batch, key)
        return state, {**metrics, "batch_reward": jnp.mean(batch.reward),
                       "batch_reward_square": jnp.mean(batch.reward**2)}


def test_training_normalises_the_rewards_the_update_sees():
    """In the training program (the path ``make_train`` runs), MAAC's updates get rewards
    normalised per robot by the buffer's statistics: mean about 0 and mean square about 1,
    where the environment's rewards are distances of order -2.5 (mean square about 7)."""
    config = TrainConfig(
        algo="maac", scenario="nominal", num_robots=3, num_envs=4, episode_length=10,
        total_env_steps=120, eval_every=40, eval_episodes=2, learning_starts=0,
        learner=dataclasses.replace(SMALL, batch_size=64),
    )
    program = make_train(config)
    program.learner = RewardSpy(config.resolved_learner)
    state = program.init(jax.random.PRNGKey(0))
    state, metrics = jax.jit(program.run, static_argnums=1)(state, 3)
    assert int(state.updates) == 3 * config.updates_per_iteration
    mean = np.asarray(metrics["batch_reward"])
    square = np.asarray(metrics["batch_reward_square"])
    raw = np.asarray(state.buffer.reward)[: int(state.buffer.episodes)]
    assert raw.mean() < -1.5 and (raw**2).mean() > 4.0  # what the environment gives
    np.testing.assert_allclose(mean, 0.0, atol=0.3)
    np.testing.assert_allclose(square, 1.0, atol=0.4)


def test_sampled_actions_follow_the_policy():
    logits = np.array([[[2.0, 0.0, -1.0, 0.5, 1.0]]], np.float32)
    draws = 20_000
    gumbel = np.random.default_rng(12).gumbel(size=(draws, 1, 5)).astype(np.float32)
    action, log_pi = sample_actions(np.repeat(logits, draws, axis=0), gumbel)
    probs = np.exp(logits[0, 0]) / np.sum(np.exp(logits[0, 0]))
    frequency = np.bincount(np.asarray(action)[:, 0], minlength=5) / draws
    np.testing.assert_allclose(frequency, probs, atol=0.015)
    np.testing.assert_allclose(np.exp(log_pi[:, 0]), probs[np.asarray(action)[:, 0]], rtol=1e-5)


def test_act_samples_or_takes_the_argmax_the_same_under_jit(setup):
    learner, state = setup
    obs = (np.random.default_rng(10).normal(size=(64, N, F)) * 3).astype(np.float32)
    act_jit = jax.jit(learner.act, static_argnums=3)
    results = {}
    for explore in (False, True):
        key = jax.random.PRNGKey(11)
        eager = learner.act(state, obs, key, explore)
        np.testing.assert_array_equal(eager, act_jit(state, obs, key, explore))
        assert eager.dtype == jnp.int32 and eager.shape == (64, N)
        assert np.all((np.asarray(eager) >= 0) & (np.asarray(eager) < A))
        results[explore] = eager
    logits = np.stack([np_mlp(robot(state.policy, i), obs[:, i]) for i in range(N)], axis=1)
    np.testing.assert_array_equal(results[False], np.argmax(logits, axis=-1))
    assert not np.array_equal(results[False], results[True])


@pytest.mark.parametrize(
    "field, value",
    [
        ("policy_hidden", ()),
        ("critic_hidden", 0),
        ("attention_heads", 3),  # must divide critic_hidden
        ("policy_lr", -1e-3),
        ("critic_lr", float("nan")),
        ("gamma", 1.0),
        ("tau", 0.0),
        ("reward_scale", 0.0),
        ("batch_size", 0),
        ("buffer_size", 2.5),
        ("update_every", 0),
        ("gradient_steps", True),
        ("critic_grad_clip_factor", float("inf")),
        ("policy_grad_clip", 0.0),
        ("critic_weight_decay", -1.0),
        ("attention_regulariser", float("nan")),
        ("policy_regulariser", -1e-3),
        ("normalise_rewards", 1),
    ],
)
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"MAACConfig.{field}"):
        MAACConfig(**{field: value})


def test_one_robot_is_refused():
    with pytest.raises(ValueError, match="at least 2 robots"):
        MAAC(SMALL).init(jax.random.PRNGKey(0), 1, F)


def test_flops_count_for_the_reference_size():
    learner = MAAC(MAACConfig(action_set="mpe5"))
    flops = learner.flops_per_update(5, 23)
    # Per robot and sample: policy 2 (23*128 + 128*128 + 128*5) = 39 936; critic
    # 2*128*28 + 2*128*23 + 6*128^2 + 4*5*128 + 2 (256*128 + 128*5) = 180 736.
    assert flops == (4 * 39_936 + 5 * 180_736) * 1024 * 5
    assert learner.flops_per_update(6, 23) > flops
    # With box9's 9 actions: policy 2 (23*128 + 128*128 + 128*9) = 40 960; critic
    # 2*128*32 + 2*128*23 + 6*128^2 + 4*5*128 + 2 (256*128 + 128*9) = 182 784.
    assert MAAC(MAACConfig()).flops_per_update(5, 23) == (4 * 40_960 + 5 * 182_784) * 1024 * 5


def test_action_set_is_validated_and_sets_the_action_count():
    assert MAACConfig().num_actions == 9 and MAACConfig(action_set="mpe5").num_actions == 5
    with pytest.raises(ValueError, match="MAACConfig.action_set must be one of"):
        MAACConfig(action_set="mpe9")
    with pytest.raises(ValueError, match=r"discrete_action_set must be one of \['box9', 'mpe5'\]"):
        EmergencyEnv("nominal", discrete_actions=True, discrete_action_set="box8")
    program = make_train(TrainConfig(algo="maac", learner=MAACConfig(action_set="mpe5"),
                                     total_env_steps=1000, learning_starts=200))
    assert program.env.action_size == 5 and program.learner.num_actions == 5


# A small MAAC on the nominal task: on each of three seeds (one vmapped program), the greedy
# policy improves clearly within 3000 environment steps (about 320 updates of batch 128).
# Sizes and tau/gamma/update rate are shrunk from the original's for speed; everything else
# is the default.
LEARNING = TrainConfig(
    algo="maac",
    scenario="nominal",
    num_envs=8,
    episode_length=25,
    total_env_steps=3000,
    eval_every=3000,
    eval_episodes=16,
    learning_starts=1000,
    learner=MAACConfig(
        policy_hidden=(32, 32),
        critic_hidden=32,
        attention_heads=2,
        batch_size=128,
        tau=0.01,
        gamma=0.95,
        update_every=25,
        gradient_steps=4,
    ),
)


@pytest.mark.slow  # a whole training program over 3 seeds: about 30 s of the fast suite
def test_maac_learns_to_reach_the_destination():
    program = make_train(LEARNING)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in (0, 1, 2)])
    state, history = jax.jit(jax.vmap(program.train))(keys)
    program.raise_if_nonfinite(state)
    returns = np.asarray(history["return"])  # [seeds, evaluations]
    # Success needs every robot in the target area at the last step, more than this budget
    # buys; the final distance to the target must shrink clearly on every seed.
    distance = np.asarray(history["target_distance"])
    assert np.all(np.asarray(state.updates) > 300)
    assert np.all(returns[:, -1] > returns[:, 0] + 20.0), returns
    assert np.all(distance[:, -1] < distance[:, 0] - 0.5), distance
