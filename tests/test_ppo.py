"""IPPO and MAPPO: PPO's equations against hand computations, the centralised value's
input, and the learners inside the training program at a tiny size."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.agents import ppo_losses as losses
from ccrjax.agents.networks import orthogonal
from ccrjax.agents.ppo import PPO, PPOConfig
from ccrjax.agents.types import Transition
from ccrjax.training import TrainConfig, make_train, run_episode

TINY = PPOConfig(actor_hidden=(8,), critic_hidden=(8,), epochs=2, minibatches=2)


def test_gae_matches_a_hand_computed_trajectory_with_episode_ends():
    # t = 1 terminates (nothing bootstrapped), t = 2 is cut by a time limit (bootstraps
    # from the state it reached, and the recursion stops), t = 3 starts a new episode.
    gamma, lam = 0.9, 0.5
    reward = jnp.array([1.0, 2.0, 3.0, 4.0])
    value = jnp.array([0.5, 1.0, 1.5, 2.0])
    next_value = jnp.array([1.0, 9.0, 7.0, 3.0])
    terminated = jnp.array([0.0, 1.0, 0.0, 0.0])
    episode_end = jnp.array([0.0, 1.0, 1.0, 0.0])
    advantage, target = losses.gae(reward, value, next_value, terminated, episode_end,
                                   gamma, lam)
    # delta = 1 + .9 - .5, 2 - 1, 3 + .9 * 7 - 1.5, 4 + .9 * 3 - 2 = 1.4, 1, 7.8, 4.7
    # A_3 = 4.7; A_2 = 7.8 (end); A_1 = 1 (end); A_0 = 1.4 + .45 * 1 = 1.85
    np.testing.assert_allclose(advantage, [1.85, 1.0, 7.8, 4.7], rtol=1e-6)
    np.testing.assert_allclose(target, [2.35, 2.0, 9.3, 6.7], rtol=1e-6)


def test_gae_without_ends_is_the_discounted_sum_of_deltas():
    key = jax.random.PRNGKey(0)
    reward, value, next_value = jax.random.normal(key, (3, 6, 2, 4))
    zeros = jnp.zeros((6, 2, 1))
    advantage, _ = losses.gae(reward, value, next_value, zeros, zeros, 0.97, 0.8)
    delta = reward + 0.97 * next_value - value
    expected = sum((0.97 * 0.8) ** k * delta[k] for k in range(6))
    np.testing.assert_allclose(advantage[0], expected, rtol=1e-5, atol=1e-6)


def test_clipped_objective_has_no_gradient_outside_the_clip_range():
    def gradient(ratio: float, advantage: float) -> float:
        return float(jax.grad(lambda lr: losses.clipped_surrogate(
            lr, jnp.array([advantage]), 0.2))(jnp.log(jnp.array([ratio])))[0])

    # The ratio past the range in the direction the advantage favours: clipped, no gradient.
    assert gradient(1.5, 2.0) == 0.0
    assert gradient(0.5, -2.0) == 0.0
    # Inside the range, or past it against the advantage: the unclipped term's gradient,
    # d(-rho A)/d(log rho) = -rho A.
    np.testing.assert_allclose(gradient(1.1, 2.0), -2.2, rtol=1e-5)
    np.testing.assert_allclose(gradient(0.5, 2.0), -1.0, rtol=1e-5)
    np.testing.assert_allclose(gradient(1.5, -2.0), 3.0, rtol=1e-5)


def test_value_loss_with_and_without_clipping():
    value, old, target = jnp.array([1.0, 1.0]), jnp.array([0.0, 0.0]), jnp.array([2.0, 0.5])
    # Unclipped: 0.5 mean((1 - 2)^2, (1 - .5)^2) = 0.5 (1 + .25) / 2.
    np.testing.assert_allclose(losses.value_loss(value, old, target, None), 0.3125)
    # Clipped at .2: the first step's clipped value .2 is further from 2 (3.24 > 1); the
    # second's (.09 < .25) is not used.
    np.testing.assert_allclose(losses.value_loss(value, old, target, 0.2),
                               0.5 * (3.24 + 0.25) / 2, rtol=1e-6)


def test_log_probabilities_and_entropies():
    mean, log_std = jnp.array([0.5, -1.0]), jnp.array([0.0, jnp.log(2.0)])
    action = jnp.array([1.0, 0.0])
    by_hand = sum(-0.5 * ((a - m) / s) ** 2 - np.log(s) - 0.5 * np.log(2 * np.pi)
                  for a, m, s in zip([1.0, 0.0], [0.5, -1.0], [1.0, 2.0], strict=True))
    np.testing.assert_allclose(losses.gaussian_log_prob(mean, log_std, action), by_hand,
                               rtol=1e-6)
    np.testing.assert_allclose(losses.gaussian_entropy(log_std, ()),
                               np.log(2.0) + 1.0 + np.log(2 * np.pi), rtol=1e-6)
    logits = jnp.log(jnp.array([0.2, 0.3, 0.5]))
    np.testing.assert_allclose(losses.categorical_log_prob(logits, jnp.array(2)), np.log(0.5),
                               rtol=1e-6)
    p = np.array([0.2, 0.3, 0.5])
    np.testing.assert_allclose(losses.categorical_entropy(logits), -np.sum(p * np.log(p)),
                               rtol=1e-6)


@pytest.mark.parametrize("shared", [True, False])
def test_mappo_values_read_the_team_and_ippo_values_the_robot(shared):
    obs = jax.random.normal(jax.random.PRNGKey(1), (3, 4, 5))
    other = obs.at[:, 2].add(1.0)  # only robot 2's observation changes
    for centralised in (True, False):
        learner = PPO(dataclasses.replace(TINY, centralised_critic=centralised,
                                          shared_parameters=shared))
        state = learner.init(jax.random.PRNGKey(2), 4, 5)
        moved = learner.value(state.critic, other) != learner.value(state.critic, obs)
        assert bool(jnp.all(moved[:, 2]))
        # Robot 0's value moves with robot 2's observation only when it sees the team.
        assert bool(jnp.all(moved[:, 0])) == centralised
        assert bool(jnp.any(moved[:, 0])) == centralised


def test_advantages_are_normalised_in_the_loss():
    # The policy loss is the same for advantages A and 10 A + 3: only their normalised
    # values enter it (the value loss reads the targets, not the advantages).
    learner = PPO(TINY)
    state = learner.init(jax.random.PRNGKey(3), 2, 4)
    keys = jax.random.split(jax.random.PRNGKey(4), 4)
    obs = jax.random.normal(keys[0], (16, 2, 4))
    action = jax.random.normal(keys[1], (16, 2, 2))
    advantage = jax.random.normal(keys[2], (16, 2))
    log_prob, _ = learner.log_prob_entropy(state.actor, obs, action)
    shift = 0.3 * jax.random.normal(keys[3], (16, 2))  # ratios spread around 1
    sample = {"obs": obs, "action": action, "log_prob": log_prob + shift,
              "value": jnp.zeros((16, 2)), "target": jnp.ones((16, 2)),
              "advantage": advantage}
    params = {"actor": state.actor, "critic": state.critic}
    _, first = learner.loss(params, sample)
    _, scaled = learner.loss(params, {**sample, "advantage": 10.0 * advantage + 3.0})
    assert abs(float(first["actor_loss"])) > 1e-3
    np.testing.assert_allclose(first["actor_loss"], scaled["actor_loss"], rtol=1e-4)
    np.testing.assert_allclose(losses.normalise(advantage).mean(), 0.0, atol=1e-6)
    np.testing.assert_allclose(losses.normalise(advantage).std(), 1.0, rtol=1e-5)


@pytest.mark.parametrize("discrete", [False, True])
def test_one_update_moves_the_policy_within_the_clip(discrete):
    learner = PPO(dataclasses.replace(TINY, discrete=discrete))
    state = learner.init(jax.random.PRNGKey(5), 3, 6)
    keys = jax.random.split(jax.random.PRNGKey(6), 4)
    steps, envs = 5, 4
    obs = jax.random.normal(keys[0], (steps, envs, 3, 6))
    action = jax.vmap(lambda o, k: learner.act(state, o, k, True))(
        obs, jax.random.split(keys[1], steps))
    assert action.dtype == (jnp.int32 if discrete else jnp.float32)
    rollout = Transition(obs=obs, action=action,
                         reward=jax.random.normal(keys[2], (steps, envs, 3)),
                         next_obs=jnp.roll(obs, -1, axis=0), done=jnp.zeros((steps, envs)))
    new_state, metrics = jax.jit(learner.update)(state, rollout, keys[3])
    assert set(metrics) == {"actor_loss", "critic_loss", "entropy", "approx_kl",
                            "clip_fraction"}
    assert all(np.isfinite(float(v)) for v in metrics.values())
    changed = jax.tree_util.tree_map(lambda a, b: bool(jnp.any(a != b)), state.actor,
                                     new_state.actor)
    assert any(jax.tree_util.tree_leaves(changed))
    # The first minibatch starts at ratio 1: the rollout's log probabilities are the
    # parameters' own, so a small step leaves the approximate KL small.
    assert 0.0 <= float(metrics["approx_kl"]) < 0.1


@pytest.mark.parametrize("shared", [True, False])
def test_an_update_makes_actions_with_positive_advantage_more_likely(shared):
    # One-step episodes whose reward is the sign of the action's x force: after an update
    # the rewarded actions' log probabilities rise against the others'.
    learner = PPO(dataclasses.replace(TINY, shared_parameters=shared, gamma=0.5))
    state = learner.init(jax.random.PRNGKey(10), 2, 3)
    keys = jax.random.split(jax.random.PRNGKey(11), 3)
    obs = jax.random.normal(keys[0], (1, 64, 2, 3))
    action = learner.act(state, obs[0], keys[1], True)[None]
    reward = jnp.sign(action[..., 0])
    rollout = Transition(obs=obs, action=action, reward=reward, next_obs=obs,
                         done=jnp.zeros((1, 64)))
    new_state, _ = jax.jit(learner.update)(state, rollout, keys[2])
    before, _ = learner.log_prob_entropy(state.actor, obs[0], action[0])
    after, _ = learner.log_prob_entropy(new_state.actor, obs[0], action[0])
    assert float(jnp.mean((after - before) * reward[0])) > 0.0


def test_ppo_config_refuses_bad_values():
    for field, value in (("clip", 0.0), ("clip", 1.5), ("gae_lambda", 0.0),
                         ("gae_lambda", 1.01), ("minibatches", 0), ("epochs", 0),
                         ("value_clip", -0.1), ("lr", float("nan"))):
        with pytest.raises(ValueError, match=field):
            PPOConfig(**{field: value})
    with pytest.raises(ValueError, match="minibatches must divide"):
        TrainConfig(algo="mappo", num_envs=3, learner=PPOConfig(minibatches=4))


def test_on_policy_learners_default_to_many_environments_and_learn_at_once():
    mappo = TrainConfig(algo="mappo")
    assert mappo.num_envs == 160 and mappo.resolved_learner.centralised_critic
    assert TrainConfig(algo="maddpg").num_envs == 8
    ippo = TrainConfig(algo="ippo", num_envs=4, total_env_steps=100)
    assert not ippo.resolved_learner.centralised_critic
    assert ippo.learning_starts_transitions == 0 and ippo.min_total_env_steps == 100
    assert TrainConfig(algo="mappo", num_envs=None) == mappo


@pytest.mark.slow  # two whole training programs compiled: about 40 s of the suite
def test_vmapped_seeds_equal_separate_runs():
    config = TrainConfig(algo="mappo", scenario="turbulence", num_envs=4, episode_length=10,
                         total_env_steps=120, eval_every=40, eval_episodes=4, learner=TINY)
    program = make_train(config)
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    _, together = jax.jit(jax.vmap(program.train))(keys)
    train = jax.jit(program.train)
    for index in range(2):
        _, alone = train(keys[index])
        for name in ("return", "danger_frequency", "success_rate"):
            np.testing.assert_allclose(together[name][index], alone[name], rtol=1e-5,
                                       atol=1e-6)
    assert together["return"].shape == (2, program.num_evaluations + 1)


def test_ccr_fits_its_model_on_the_first_rollout_of_the_initial_policy():
    # PPO has no random warm-up: CCR's model is fitted at each episode's start from the
    # rollouts of the initial, nearly random policy (its robust weights settle over the
    # first few). After three, the model predicts the robots' motion: the typical score is
    # far below their squared displacement, which a "nothing moves" model would score.
    config = TrainConfig(algo="mappo", variant="ccr", scenario="nominal", num_envs=8,
                         total_env_steps=600, eval_every=200, learner=TINY)
    program = make_train(config)
    state = program.init(jax.random.PRNGKey(8))
    state, _ = jax.jit(lambda s: program.run(s, 3))(state)
    assert float(state.transform.statistics.total_weight) > 0

    def explore(obs, key):
        return program.learner.act(state.learner, obs, key, True)

    _, episode = jax.jit(lambda key: run_episode(
        program.env, program.transform, state.transform, explore, False, key))(
        jax.random.PRNGKey(9))
    displacement = jnp.sum(jnp.square(jnp.diff(episode.position, axis=0)), axis=2)
    assert float(jnp.mean(displacement)) > 1e-3  # the robots move
    score = episode.info["emergency_score"]  # the tail: robots bumping into each other
    assert float(jnp.median(score)) < 1e-3 * float(jnp.mean(displacement))


def train_seeds(config: TrainConfig, seeds=(0, 1, 2)) -> dict:
    """The evaluation history of every seed, trained side by side, leaves ``[seeds, points]``."""
    program = make_train(config)
    keys = jnp.stack([jax.random.PRNGKey(seed) for seed in seeds])
    state, history = jax.jit(jax.vmap(program.train))(keys)
    program.raise_if_nonfinite(state)
    return {name: np.asarray(values) for name, values in history.items()}


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ippo", "mappo"])
def test_ippo_and_mappo_learn_nominal_on_every_seed(algo):
    # The defaults (160 environments) at about half their budget: the calibration curve
    # (experiments/results/calibration/ppo_nominal_160_envs.txt) is above 93% there.
    history = train_seeds(TrainConfig(algo=algo, scenario="nominal", total_env_steps=160_000,
                                      eval_every=160_000, eval_episodes=64))
    success = history["success_rate"][:, -1]
    print(f"{algo} on nominal: success {success}")
    assert np.all(success >= 0.9), success


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ippo", "mappo"])
def test_ippo_and_mappo_improve_their_return_with_a_hazard(algo):
    history = train_seeds(TrainConfig(algo=algo, scenario="hidden_obstacle",
                                      total_env_steps=160_000, eval_every=160_000,
                                      eval_episodes=64))
    initial, final = history["return"][:, 0], history["return"][:, -1]
    print(f"{algo} on the hidden obstacle: return {initial.round(1)} -> {final.round(1)}, "
          f"success {history['success_rate'][:, -1]}")
    # Returns are negative distances summed over the episode: improving = closer to 0.
    assert np.all(final > initial + 0.3 * np.abs(initial)), (initial, final)


@pytest.mark.parametrize("shape", [(64, 64), (30, 64), (64, 2), (3, 4, 5)])
def test_the_orthogonal_initialisation_is_jaxs_without_a_lapack_call(shape):
    """The networks' orthogonal kernels equal jax's initializer's to float rounding, with
    orthonormal rows or columns, and a grid of seeds initialises them without the batched QR
    custom call that can deadlock XLA's CPU thread pool."""
    key = jax.random.PRNGKey(7)
    ours = orthogonal(1.5)(key, shape)
    np.testing.assert_allclose(ours, jax.nn.initializers.orthogonal(1.5)(key, shape),
                               atol=5e-6)
    matrix = np.asarray(ours).reshape(-1, shape[-1]) / 1.5
    small = min(matrix.shape)
    gram = matrix.T @ matrix if matrix.shape[0] >= matrix.shape[1] else matrix @ matrix.T
    np.testing.assert_allclose(gram, np.eye(small), atol=5e-6)
    def primitives(initializer) -> set[str]:
        text = str(jax.make_jaxpr(jax.vmap(lambda k: initializer(k, shape)))(
            jax.random.split(key, 4)))
        return set(re.findall(r"= ([a-z_]+)\[", text))

    assert "qr" in primitives(jax.nn.initializers.orthogonal(1.0))  # what is avoided
    assert "qr" not in primitives(orthogonal(1.0))
