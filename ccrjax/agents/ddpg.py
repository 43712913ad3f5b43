"""Independent DDPG and MADDPG: one implementation, the critic's input is the only difference.

Each robot ``i`` has a deterministic actor ``mu_i(o_i) = tanh(pre_i(o_i))`` and a
critic ``Q_i``. MADDPG (Lowe et al. 2017) gives ``Q_i`` every robot's observation
and action, ``Q_i(o_1..o_N, a_1..a_N)``; independent DDPG (the paper's "DDPG")
gives it only robot ``i``'s own, ``Q_i(o_i, a_i)``. Defaults are the original
MADDPG code's (``docs/references.md`` section 2): 64-64 ReLU networks, gamma 0.95, Polyak
tau 0.01, batch 1024, gradients clipped to norm 0.5 per variable, one update every
100 environment steps; two measured exceptions, documented at the fields: Adam's
learning rate is 1e-3 (not 1e-2) and the exploration noise 0.3.

One update (for all robots at once, their parameters stacked on a robot axis):

* critic: ``y_i = r_i + gamma (1 - done) Q'_i(o', mu'_1(o'_1) .. mu'_N(o'_N))``,
  loss ``mean (Q_i(o, a) - y_i)^2`` (targets from the target networks);
* actor, with the updated critic: ``-mean Q_i(o, a_1 .. mu_i(o_i) .. a_N) +
  1e-3 mean(pre_i^2)``, the other robots' actions taken from the buffer;
* targets: ``theta' <- (1 - tau) theta' + tau theta``.

The paper runs both with continuous actions, so exploration adds Gaussian noise
(standard deviation ``exploration_noise``) to the tanh output and clips to
``[-1, 1]``; the original's Gumbel-softmax belongs to its discrete actions.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from ccrjax.agents.networks import MLP, apply_per_robot, init_per_robot, mlp_flops
from ccrjax.agents.types import Transition, soft_update
from ccrjax.checks import check_finite, check_hidden, check_positive_int

ACTION_SIZE = 2


@dataclasses.dataclass(frozen=True)
class DDPGConfig:
    """Hyperparameters of independent DDPG / MADDPG (defaults: the original MADDPG)."""

    centralised_critic: bool = True  # critic sees every robot (MADDPG) or its own (IDDPG)
    actor_hidden: tuple[int, ...] = (64, 64)  # hidden layer widths of each robot's actor
    critic_hidden: tuple[int, ...] = (64, 64)  # hidden layer widths of each robot's critic
    actor_lr: float = 1e-3  # Adam learning rate of the actors
    critic_lr: float = 1e-3  # Adam learning rate of the critics
    gamma: float = 0.95  # discount factor
    tau: float = 0.01  # Polyak rate of the target networks
    batch_size: int = 1024  # transitions per update
    buffer_size: int = 1_000_000  # replay capacity (capped by the run's transitions)
    grad_clip: float = 0.5  # gradient norm clip, per variable
    actor_regulariser: float = 1e-3  # weight of the squared pre-activation penalty
    exploration_noise: float = 0.3  # std of the exploration noise on the action
    update_every: int = 100  # environment steps between rounds of updates
    gradient_steps: int = 1  # updates per round

    def __post_init__(self) -> None:
        owner = "DDPGConfig"
        check_hidden(owner, "actor_hidden", self.actor_hidden)
        check_hidden(owner, "critic_hidden", self.critic_hidden)
        check_finite(owner, "actor_lr", self.actor_lr)
        check_finite(owner, "critic_lr", self.critic_lr)
        check_finite(owner, "gamma", self.gamma, low=0.0, low_open=False, high=1.0, high_open=True)
        check_finite(owner, "tau", self.tau, high=1.0)
        check_positive_int(owner, "batch_size", self.batch_size)
        check_positive_int(owner, "buffer_size", self.buffer_size)
        check_finite(owner, "grad_clip", self.grad_clip)
        check_finite(owner, "actor_regulariser", self.actor_regulariser, low_open=False)
        check_finite(owner, "exploration_noise", self.exploration_noise, low_open=False)
        check_positive_int(owner, "update_every", self.update_every)
        check_positive_int(owner, "gradient_steps", self.gradient_steps)


@struct.dataclass
class DDPGState:
    """Parameters (stacked on a leading robot axis), their targets and optimiser states."""

    actor: Any
    critic: Any
    target_actor: Any
    target_critic: Any
    actor_opt: Any
    critic_opt: Any


def clip_per_variable(grads: Any, max_norm: float) -> Any:
    """Clips each robot's gradient of each variable to norm ``max_norm`` (the original's
    ``tf.clip_by_norm`` per variable); leaves carry a leading robot axis."""

    def clip(g: jax.Array) -> jax.Array:
        norm = jnp.sqrt(jnp.sum(g.reshape(g.shape[0], -1) ** 2, axis=1))
        scale = jnp.where(norm > max_norm, max_norm / jnp.where(norm > 0, norm, 1.0), 1.0)
        return g * scale.reshape((-1,) + (1,) * (g.ndim - 1))

    return jax.tree_util.tree_map(clip, grads)


class DDPG:
    """MADDPG (``centralised_critic=True``) or independent DDPG (``False``)."""

    discrete = False

    def __init__(self, config: DDPGConfig = DDPGConfig()) -> None:
        self.config = config
        self.name = "maddpg" if config.centralised_critic else "iddpg"
        self.needs_reward_stats = False  # DDPG learns from the rewards as they are
        self.actor = MLP(config.actor_hidden, ACTION_SIZE)
        self.critic = MLP(config.critic_hidden, 1)
        self.actor_optimiser = optax.adam(config.actor_lr)
        self.critic_optimiser = optax.adam(config.critic_lr)

    # ------------------------------------------------------------ critic input
    def critic_input(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        """What each robot's critic sees, ``[batch, N, D]``.

        MADDPG: every robot's observation and action, the same for all ``i``:
        ``D = N (F + 2)``. Independent DDPG: robot ``i``'s own: ``D = F + 2``.
        """
        if not self.config.centralised_critic:
            return jnp.concatenate([obs, action], axis=-1)
        batch, num_robots = obs.shape[:2]
        joint = jnp.concatenate(
            [obs.reshape(batch, -1), action.reshape(batch, -1)], axis=-1
        )
        return jnp.broadcast_to(joint[:, None], (batch, num_robots, joint.shape[-1]))

    def critic_input_with_own(self, obs: jax.Array, action: jax.Array, own: jax.Array):
        """Critic inputs where robot ``i``'s action is replaced by ``own[:, i]``.

        MADDPG: row ``i`` holds the buffer's actions of the others and ``own[:, i]``.
        """
        if not self.config.centralised_critic:
            return jnp.concatenate([obs, own], axis=-1)
        batch, num_robots = obs.shape[:2]
        eye = jnp.eye(num_robots, dtype=bool)[None, :, :, None]  # [1, i, j, 1]
        actions = jnp.where(eye, own[:, None, :, :], action[:, None, :, :])  # [b, i, j, A]
        flat_obs = jnp.broadcast_to(
            obs.reshape(batch, 1, -1), (batch, num_robots, obs.shape[1] * obs.shape[2])
        )
        return jnp.concatenate([flat_obs, actions.reshape(batch, num_robots, -1)], axis=-1)

    def critic_input_size(self, num_robots: int, obs_size: int) -> int:
        per_robot = obs_size + ACTION_SIZE
        return num_robots * per_robot if self.config.centralised_critic else per_robot

    # ------------------------------------------------------------ interface
    def normalise_rewards(self, batch: Transition, mean: jax.Array, std: jax.Array
                          ) -> Transition:
        """The batch unchanged: DDPG does not normalise rewards."""
        return batch

    def init(self, key: jax.Array, num_robots: int, obs_size: int) -> DDPGState:
        actor_key, critic_key = jax.random.split(key)
        actor = init_per_robot(self.actor, actor_key, num_robots, jnp.zeros((1, obs_size)))
        critic = init_per_robot(
            self.critic,
            critic_key,
            num_robots,
            jnp.zeros((1, self.critic_input_size(num_robots, obs_size))),
        )
        return DDPGState(
            actor=actor,
            critic=critic,
            target_actor=actor,
            target_critic=critic,
            actor_opt=self.actor_optimiser.init(actor),
            critic_opt=self.critic_optimiser.init(critic),
        )

    def policy(self, actor_params: Any, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Deterministic actions ``tanh(pre)`` and the pre-activations, ``[batch, N, 2]``."""
        pre = apply_per_robot(self.actor, actor_params, obs)
        return jnp.tanh(pre), pre

    def act(self, state: DDPGState, obs: jax.Array, key: jax.Array, explore: bool) -> jax.Array:
        action, _ = self.policy(state.actor, obs)
        if explore and self.config.exploration_noise > 0:
            noise = self.config.exploration_noise * jax.random.normal(key, action.shape)
            action = jnp.clip(action + noise, -1.0, 1.0)
        return action

    def q_values(self, critic_params: Any, inputs: jax.Array) -> jax.Array:
        return apply_per_robot(self.critic, critic_params, inputs)[..., 0]

    def td_target(self, state: DDPGState, batch: Transition) -> jax.Array:
        """``y_i = r_i + gamma (1 - done) Q'_i(o', mu'(o'))``, ``[batch, N]``."""
        next_action, _ = self.policy(state.target_actor, batch.next_obs)
        next_q = self.q_values(state.target_critic, self.critic_input(batch.next_obs, next_action))
        return batch.reward + self.config.gamma * (1.0 - batch.done)[:, None] * next_q

    def update(self, state: DDPGState, batch: Transition, key: jax.Array):
        del key
        config = self.config
        target = jax.lax.stop_gradient(self.td_target(state, batch))
        inputs = self.critic_input(batch.obs, batch.action)

        def critic_loss(params):
            q = self.q_values(params, inputs)
            # Summed over robots: robot i's loss depends only on robot i's parameters.
            return jnp.sum(jnp.mean((q - target) ** 2, axis=0)), q

        (c_loss, q), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(state.critic)
        c_grads = clip_per_variable(c_grads, config.grad_clip)
        c_updates, critic_opt = self.critic_optimiser.update(c_grads, state.critic_opt)
        critic = optax.apply_updates(state.critic, c_updates)

        def actor_loss(params):
            own, pre = self.policy(params, batch.obs)
            q_own = self.q_values(critic, self.critic_input_with_own(batch.obs, batch.action, own))
            per_robot = -jnp.mean(q_own, axis=0) + config.actor_regulariser * jnp.mean(
                pre**2, axis=(0, 2)
            )
            return jnp.sum(per_robot)

        a_loss, a_grads = jax.value_and_grad(actor_loss)(state.actor)
        a_grads = clip_per_variable(a_grads, config.grad_clip)
        a_updates, actor_opt = self.actor_optimiser.update(a_grads, state.actor_opt)
        actor = optax.apply_updates(state.actor, a_updates)

        num_robots = batch.reward.shape[1]
        new_state = DDPGState(
            actor=actor,
            critic=critic,
            target_actor=soft_update(state.target_actor, actor, config.tau),
            target_critic=soft_update(state.target_critic, critic, config.tau),
            actor_opt=actor_opt,
            critic_opt=critic_opt,
        )
        metrics = {
            "critic_loss": c_loss / num_robots,
            "actor_loss": a_loss / num_robots,
            "q_mean": jnp.mean(q),
        }
        return new_state, metrics

    def flops_per_update(self, num_robots: int, obs_size: int) -> float:
        """Matrix-multiply FLOPs of one update: forward 1x, backward 2x per network pass.

        Per robot and sample: target actor and critic forward (A + C), critic loss
        forward and backward (3 C), actor loss forward and backward through actor
        and critic (3 A + 3 C): ``4 A + 7 C``.
        """
        c = self.config
        actor = mlp_flops([obs_size, *c.actor_hidden, ACTION_SIZE])
        critic = mlp_flops([self.critic_input_size(num_robots, obs_size), *c.critic_hidden, 1])
        per_sample = 4 * actor + 7 * critic
        return float(np.float64(per_sample) * c.batch_size * num_robots)
