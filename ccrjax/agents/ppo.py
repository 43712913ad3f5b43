"""IPPO and MAPPO: PPO per robot, with the value function seeing the robot's own
observation (IPPO) or the whole team's (MAPPO), one implementation.

An on-policy :class:`ccrjax.agents.types.Learner` (``on_policy = True``): the training
program hands :meth:`PPO.update` each iteration's rollout, one episode of every training
environment (``[T, E, ...]``), instead of batches sampled from a replay buffer. One update:

1. the rollout's log probabilities, values ``V(s_t)`` and ``V(s_{t+1})`` under the
   parameters that collected it (they are the current ones: PPO updates only here);
2. generalised advantage estimates and value targets (:func:`ppo_losses.gae`); the
   particle tasks end by time limit only, so the last step bootstraps from the state
   reached (Pardo et al. 2018, as the off-policy learners' targets do);
3. ``epochs`` passes over the rollout's team-steps in ``minibatches`` shuffled minibatches,
   each one Adam step on ``L^CLIP + c_v L^V - c_e H`` (advantages normalised per minibatch,
   the value loss clipped, the gradient clipped to a global norm), PureJaxRL's layout.

**Actions.** Continuous: a diagonal Gaussian over the 2-D force whose mean is the network's
output and whose log standard deviation is a learned, state-independent parameter; the
sample is stored as drawn (its log probability is exact) and the world clips it to
``[-1, 1]``, as it clips every learner's force (PureJaxRL's ``ClipAction``); evaluation acts
with the mean. Discrete (``discrete=True``): a categorical over ``action_set`` (``box9``
by default, MAAC's), evaluation with the most probable action.

**Who sees what.** ``shared_parameters`` (MAPPO's default): one actor and one critic for
every robot, each robot's input carrying its one-hot index; otherwise one network per robot,
stacked on a robot axis. MAPPO's critic input is every robot's observation concatenated (the
world has no separate global state; the concatenation holds everything any robot senses, the
MAPPO paper's choice for the MPE), with the robot's index.

Defaults: 64-64 tanh networks with orthogonal initialisation (gain sqrt 2, 0.01 on the policy
head, 1 on the value head), Adam 5e-4, gamma 0.99, GAE lambda 0.95, clip 0.2 for the ratio and
the value, 4 epochs of 4 minibatches, entropy 0.0, value coefficient 0.5, gradient norm 0.5;
no learning-rate annealing, so that a run is the first part of a longer one.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from ccrjax.agents import ppo_losses as losses
from ccrjax.agents.networks import init_per_robot, mlp_flops, orthogonal
from ccrjax.agents.types import Transition
from ccrjax.checks import check_choice, check_finite, check_hidden, check_positive_int
from ccrjax.envs.world import DEFAULT_DISCRETE_ACTION_SET, DISCRETE_ACTION_SETS

ACTION_SIZE = 2


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Hyperparameters of IPPO / MAPPO (the module docstring says where they come from)."""

    centralised_critic: bool = True  # the value sees the team (MAPPO) or the robot (IPPO)
    shared_parameters: bool = True  # one network for all robots, robot index in the input
    discrete: bool = False  # a categorical over action_set instead of a Gaussian force
    action_set: str = DEFAULT_DISCRETE_ACTION_SET  # discrete actions: box9 or mpe5
    actor_hidden: tuple[int, ...] = (64, 64)  # hidden layer widths of the policy
    critic_hidden: tuple[int, ...] = (64, 64)  # hidden layer widths of the value function
    lr: float = 5e-4  # Adam learning rate (policy and value)
    gamma: float = 0.99  # discount factor
    gae_lambda: float = 0.95  # GAE's lambda, in (0, 1]
    clip: float = 0.2  # the ratio's clip range eps, in (0, 1]
    value_clip: float = 0.2  # the value's clip range; 0: no value clipping
    epochs: int = 4  # passes over each rollout
    minibatches: int = 4  # minibatches per pass; must divide the rollout's team-steps
    entropy_coef: float = 0.0  # weight of the entropy bonus
    value_coef: float = 0.5  # weight of the value loss
    max_grad_norm: float = 0.5  # global gradient norm clip
    init_log_std: float = 0.0  # the Gaussian's initial log standard deviation

    def __post_init__(self) -> None:
        owner = "PPOConfig"
        check_hidden(owner, "actor_hidden", self.actor_hidden)
        check_hidden(owner, "critic_hidden", self.critic_hidden)
        check_choice(owner, "action_set", self.action_set, DISCRETE_ACTION_SETS)
        check_finite(owner, "lr", self.lr)
        check_finite(owner, "gamma", self.gamma, low=0.0, low_open=False, high=1.0,
                     high_open=True)
        check_finite(owner, "gae_lambda", self.gae_lambda, high=1.0)
        check_finite(owner, "clip", self.clip, high=1.0)
        check_finite(owner, "value_clip", self.value_clip, low_open=False)
        check_positive_int(owner, "epochs", self.epochs)
        check_positive_int(owner, "minibatches", self.minibatches)
        check_finite(owner, "entropy_coef", self.entropy_coef, low_open=False)
        check_finite(owner, "value_coef", self.value_coef)
        check_finite(owner, "max_grad_norm", self.max_grad_norm)
        check_finite(owner, "init_log_std", self.init_log_std, low=-20.0, high=2.0)

    def rollout_problem(self, num_envs: int, episode_length: int) -> str | None:
        """Why a rollout of ``num_envs`` x ``episode_length`` team-steps cannot be cut into
        ``minibatches`` equal minibatches (``None`` if it can)."""
        steps = num_envs * episode_length
        if steps % self.minibatches:
            return (f"PPOConfig.minibatches must divide the rollout's {steps:,} team-steps "
                    f"(num_envs {num_envs} x episode_length {episode_length}), got "
                    f"{self.minibatches}")
        return None

    @property
    def num_actions(self) -> int:
        """The policy head's width: the force's 2 means, or the action set's size."""
        return len(DISCRETE_ACTION_SETS[self.action_set]) if self.discrete else ACTION_SIZE


class PPONetwork(nn.Module):
    """A tanh MLP with orthogonal initialisation (:func:`networks.orthogonal`, computed
    without LAPACK so that a grid of seeds cannot deadlock on CPU); with ``log_std``, it also
    owns the Gaussian policy's state-independent log standard deviation."""

    hidden: tuple[int, ...]
    out: int
    head_gain: float
    log_std: float | None = None

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        for width in self.hidden:
            x = nn.tanh(nn.Dense(width, kernel_init=orthogonal(np.sqrt(2.0)))(x))
        head = nn.Dense(self.out, kernel_init=orthogonal(self.head_gain))(x)
        if self.log_std is None:
            return head, jnp.zeros((), head.dtype)
        log_std = self.param("log_std", nn.initializers.constant(self.log_std), (self.out,))
        return head, log_std


@struct.dataclass
class PPOState:
    """The policy's and value function's parameters (stacked on a robot axis unless shared),
    and the one Adam state over both."""

    actor: Any
    critic: Any
    opt: Any


class PPO:
    """MAPPO (``centralised_critic=True``) or IPPO (``False``); see the module docstring."""

    on_policy = True
    needs_reward_stats = False  # rewards enter GAE as they are

    def __init__(self, config: PPOConfig = PPOConfig()) -> None:
        self.config = config
        self.name = "mappo" if config.centralised_critic else "ippo"
        self.discrete = config.discrete
        gaussian = None if config.discrete else config.init_log_std
        self.actor = PPONetwork(config.actor_hidden, config.num_actions, 0.01, gaussian)
        self.critic = PPONetwork(config.critic_hidden, 1, 1.0)
        self.optimiser = optax.chain(optax.clip_by_global_norm(config.max_grad_norm),
                                     optax.adam(config.lr, eps=1e-5))

    # ------------------------------------------------------------ inputs
    def with_index(self, x: jax.Array) -> jax.Array:
        """``x`` ``[B, N, D]`` with each robot's one-hot index appended when parameters are
        shared (a shared network must know whose input it reads)."""
        if not self.config.shared_parameters:
            return x
        batch, num_robots = x.shape[:2]
        eye = jnp.broadcast_to(jnp.eye(num_robots, dtype=x.dtype), (batch, num_robots,
                                                                     num_robots))
        return jnp.concatenate([x, eye], axis=-1)

    def critic_input(self, obs: jax.Array) -> jax.Array:
        """What each robot's value function reads, ``[B, N, D]``: MAPPO every robot's
        observation (``D = N F``), IPPO its own (``D = F``), with the index if shared."""
        if self.config.centralised_critic:
            batch, num_robots = obs.shape[:2]
            team = obs.reshape(batch, -1)
            obs = jnp.broadcast_to(team[:, None], (batch, num_robots, team.shape[-1]))
        return self.with_index(obs)

    def apply(self, module: PPONetwork, params: Any, x: jax.Array):
        if self.config.shared_parameters:
            return module.apply(params, x)
        return jax.vmap(module.apply, in_axes=(0, 1), out_axes=(1, 0))(params, x)

    # ------------------------------------------------------------ state
    def init(self, key: jax.Array, num_robots: int, obs_size: int) -> PPOState:
        actor_key, critic_key = jax.random.split(key)
        example = jnp.zeros((1, num_robots, obs_size), jnp.float32)
        actor_x, critic_x = self.with_index(example), self.critic_input(example)
        if self.config.shared_parameters:
            actor = self.actor.init(actor_key, actor_x)
            critic = self.critic.init(critic_key, critic_x)
        else:
            actor = init_per_robot(self.actor, actor_key, num_robots, actor_x[:, 0])
            critic = init_per_robot(self.critic, critic_key, num_robots, critic_x[:, 0])
        return PPOState(actor=actor, critic=critic,
                        opt=self.optimiser.init({"actor": actor, "critic": critic}))

    # ------------------------------------------------------------ policy and value
    def policy(self, actor: Any, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The policy head (means or logits, ``[B, N, K]``) and the log standard deviation
        (``[K]``, or ``[N, K]`` for unshared parameters; 0 for discrete actions)."""
        return self.apply(self.actor, actor, self.with_index(obs))

    def value(self, critic: Any, obs: jax.Array) -> jax.Array:
        """``V_i(s)`` for every robot, ``[B, N]``."""
        value, _ = self.apply(self.critic, critic, self.critic_input(obs))
        return value[..., 0]

    def log_prob_entropy(self, actor: Any, obs: jax.Array, action: jax.Array
                         ) -> tuple[jax.Array, jax.Array]:
        """``log pi_i(a_i | o_i)`` and the policy's entropy per robot, ``[B, N]`` each."""
        head, log_std = self.policy(actor, obs)
        if self.discrete:
            return (losses.categorical_log_prob(head, action),
                    losses.categorical_entropy(head))
        log_std = jnp.broadcast_to(log_std, head.shape)
        return (losses.gaussian_log_prob(head, log_std, action),
                losses.gaussian_entropy(log_std, head.shape[:-1]))

    def act(self, state: PPOState, obs: jax.Array, key: jax.Array, explore: bool) -> jax.Array:
        """A sample of the policy (``explore``), or its mean / most probable action."""
        head, log_std = self.policy(state.actor, obs)
        if self.discrete:
            if explore:
                return jax.random.categorical(key, head, axis=-1).astype(jnp.int32)
            return jnp.argmax(head, axis=-1).astype(jnp.int32)
        if not explore:
            return head
        noise = jax.random.normal(key, head.shape, head.dtype)
        return head + jnp.exp(jnp.broadcast_to(log_std, head.shape)) * noise

    def normalise_rewards(self, batch: Transition, mean: jax.Array, std: jax.Array
                          ) -> Transition:
        return batch  # never called: needs_reward_stats is False

    # ------------------------------------------------------------ update
    def loss(self, params: dict, sample: dict) -> tuple[jax.Array, dict]:
        """``L^CLIP + c_v L^V - c_e H`` on one minibatch of team-steps."""
        config = self.config
        log_prob, entropy = self.log_prob_entropy(params["actor"], sample["obs"],
                                                  sample["action"])
        log_ratio = log_prob - sample["log_prob"]
        advantage = losses.normalise(sample["advantage"])
        actor_loss = losses.clipped_surrogate(log_ratio, advantage, config.clip)
        value = self.value(params["critic"], sample["obs"])
        critic_loss = losses.value_loss(value, sample["value"], sample["target"],
                                        config.value_clip if config.value_clip > 0 else None)
        entropy = jnp.mean(entropy)
        total = actor_loss + config.value_coef * critic_loss - config.entropy_coef * entropy
        ratio = jnp.exp(log_ratio)
        return total, {
            "actor_loss": actor_loss, "critic_loss": critic_loss, "entropy": entropy,
            "approx_kl": jnp.mean((ratio - 1.0) - log_ratio),  # Schulman's k3 estimator
            "clip_fraction": jnp.mean((jnp.abs(ratio - 1.0) > config.clip).astype(jnp.float32)),
        }

    def rollout_samples(self, state: PPOState, rollout: Transition) -> dict:
        """The rollout's team-steps, flattened to ``[T E, ...]``, with their log
        probabilities, values, advantages and value targets (steps 1 and 2 above)."""
        config = self.config
        steps, envs, num_robots = rollout.reward.shape

        def flat(x: jax.Array) -> jax.Array:
            return x.reshape((steps * envs,) + x.shape[2:])

        obs, action = flat(rollout.obs), flat(rollout.action)
        log_prob, _ = self.log_prob_entropy(state.actor, obs, action)
        value = self.value(state.critic, obs)
        next_value = self.value(state.critic, flat(rollout.next_obs))
        shape = (steps, envs, num_robots)
        # One episode per environment: the array's end is every episode's end.
        advantage, target = losses.gae(
            rollout.reward, value.reshape(shape), next_value.reshape(shape),
            rollout.done[..., None], jnp.zeros((steps, envs, 1)), config.gamma,
            config.gae_lambda)
        return {"obs": obs, "action": action, "log_prob": log_prob, "value": value,
                "advantage": flat(advantage), "target": flat(target)}

    def update(self, state: PPOState, rollout: Transition, key: jax.Array
               ) -> tuple[PPOState, dict]:
        """Every epoch and minibatch of one rollout (leaves ``[T, E, ...]``); returns the
        state and the means of the minibatches' losses and diagnostics."""
        config = self.config
        samples = self.rollout_samples(state, rollout)
        count = samples["obs"].shape[0]
        size = count // config.minibatches

        def minibatch_step(carry, sample):
            params, opt = carry
            grads, metrics = jax.grad(self.loss, has_aux=True)(params, sample)
            updates, opt = self.optimiser.update(grads, opt, params)
            return (optax.apply_updates(params, updates), opt), metrics

        def epoch(carry, epoch_key):
            order = jax.random.permutation(epoch_key, count)
            shuffled = jax.tree_util.tree_map(
                lambda x: x[order].reshape((config.minibatches, size) + x.shape[1:]), samples)
            return jax.lax.scan(minibatch_step, carry, shuffled)

        params = {"actor": state.actor, "critic": state.critic}
        (params, opt), metrics = jax.lax.scan(epoch, (params, state.opt),
                                              jax.random.split(key, config.epochs))
        new_state = PPOState(actor=params["actor"], critic=params["critic"], opt=opt)
        return new_state, jax.tree_util.tree_map(jnp.mean, metrics)

    def flops_per_update(self, num_robots: int, obs_size: int, samples: int = 1) -> float:
        """Floating-point operations of one :meth:`update` on ``samples`` team-steps: the
        rollout's forward passes (policy once, value twice), then per epoch a forward and
        backward pass (about 3 forwards) of both networks on every sample."""
        config = self.config
        index = num_robots if config.shared_parameters else 0
        actor = mlp_flops((obs_size + index, *config.actor_hidden, config.num_actions))
        critic_in = (num_robots * obs_size if config.centralised_critic else obs_size) + index
        critic = mlp_flops((critic_in, *config.critic_hidden, 1))
        per_robot = (actor + 2 * critic) + config.epochs * 3 * (actor + critic)
        return float(per_robot * num_robots * samples)
