"""MAAC: Multi-Actor-Attention-Critic (Iqbal & Sha 2019), a soft actor-critic with an
attention critic over discrete actions.

Each robot ``i`` has a stochastic policy ``pi_i(a | o_i)``, a softmax over the ``A``
discrete actions (9 by default, ``MAACConfig.action_set``) computed by an MLP (two
128-unit leaky-ReLU layers). The critic gives every robot a Q value for each of its
actions, attending over the others:

* encoders, one per robot: ``e_j = leaky(W_j^e [o_j, onehot(a_j)])`` and
  ``s_i = leaky(W_i^s o_i)``;
* per attention head ``h`` (weights shared by all robots, no bias on keys and queries):
  keys ``k_j = W_k^h e_j``, query ``q_i = W_q^h s_i``, values ``v_j = leaky(W_v^h e_j + b_v^h)``;
* attention of robot ``i`` over the *other* robots only:
  ``alpha_ij = softmax_{j != i}(q_i . k_j / sqrt(d))`` (``d`` = hidden / heads),
  ``x_i^h = sum_{j != i} alpha_ij v_j``;
* ``Q_i(o, .) = head_i([s_i, x_i^1 .. x_i^H])``, a vector over robot ``i``'s actions;
  ``Q_i(o, a)`` is its entry ``a_i``. Robot ``i``'s own action enters only through
  the entry picked, so the vector is exactly ``Q_i(o, (a, a_-i))`` for every ``a``.

One update (:meth:`MAAC.update`, all robots at once, in the original's order):

* critic: ``y_i = r_i + gamma (1 - done) Q'_i(o', a') - log pi'_i(a'_i | o'_i) / reward_scale``
  with ``a'_j ~ pi'_j(. | o'_j)`` sampled from the *target* policies and ``Q'`` the
  target critic; loss ``sum_i [mean (Q_i(o, a) - y_i)^2 + 1e-3 sum_h mean_{b, j != i}
  (q_i . k_j)^2]`` (the attention regulariser acts on the unscaled logits, as in the
  original); the gradients of the modules every robot's loss goes through (the
  key/query/value extractors and the state-action encoders ``e_j``) are scaled by
  ``1/N``; the whole critic gradient is clipped to global norm ``10 N``; Adam with
  ``1e-3`` L2 weight decay added to the gradient (torch's ``Adam(weight_decay=...)``);
* policies, with the updated critic and actions ``a ~ pi(. | o)`` sampled from the
  current policies for *every* robot: baseline ``b_i = sum_a pi_i(a | o_i) Q_i(o, (a, a_-i))``,
  advantage ``A_i = Q_i(o, a) - b_i``, loss ``mean[log pi_i(a_i) * sg(log pi_i(a_i) /
  reward_scale - A_i)] + 1e-3 mean(logits^2)`` (``sg``: no gradient); each robot's
  policy gradient is clipped to global norm 0.5; Adam;
* targets: ``theta' <- (1 - tau) theta' + tau theta`` for the critic and the policies.

Rewards are normalised per robot by the replay buffer's statistics before the update
(:meth:`MAAC.normalise_rewards`; the original divides ``r - mean`` by the standard
deviation of the rewards in its buffer).

Defaults are the original's (``docs/references.md`` section 3). Known differences: the original
puts an affine-free ``BatchNorm1d`` in front of every encoder and policy; ccrjax's
observations are already of order one (positions and distances in an arena a few
units wide, unit directions), so the inputs go in as they are. Weights are initialised
as flax's ``Dense`` does (LeCun normal, zero biases;
:func:`ccrjax.agents.maac_parts.lecun_init`) rather than with torch's uniform. Random draws
are few on purpose (one for all initial weights, one Gumbel draw per update): on the CPU each
separate draw adds seconds to compilation.
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

from ccrjax.agents.maac_parts import (
    SHARED_CRITIC_MODULES,
    attend,
    attention_logit_penalty,
    baseline,
    leaky,
    lecun_init,
    per_robot_shapes,
    sample_actions,
    select,
)
from ccrjax.agents.networks import MLP, apply_per_robot, clip_by_global_norm_per_robot, mlp_flops
from ccrjax.agents.types import Transition, soft_update
from ccrjax.checks import check_choice, check_finite, check_hidden, check_positive_int
from ccrjax.envs.world import DEFAULT_DISCRETE_ACTION_SET, DISCRETE_ACTION_SETS

REWARD_STD_EPS = 1e-6  # guards the reward normalisation against a zero spread


@dataclasses.dataclass(frozen=True)
class MAACConfig:
    """Hyperparameters of MAAC (defaults: the original implementation's)."""

    policy_hidden: tuple[int, ...] = (128, 128)  # hidden layer widths of each robot's policy
    critic_hidden: int = 128  # width of the attention critic
    attention_heads: int = 4  # attention heads (each critic_hidden / heads wide)
    policy_lr: float = 1e-3  # Adam learning rate of the policies
    critic_lr: float = 1e-3  # Adam learning rate of the critic
    gamma: float = 0.99  # discount factor
    tau: float = 1e-3  # Polyak rate of the target networks
    reward_scale: float = 100.0  # entropy temperature is 1 / reward_scale
    batch_size: int = 1024  # transitions per update
    buffer_size: int = 1_000_000  # replay capacity (capped by the run's transitions)
    update_every: int = 100  # environment steps between rounds of updates
    gradient_steps: int = 4  # updates per round
    critic_grad_clip_factor: float = 10.0  # critic grad norm clipped to this x N
    policy_grad_clip: float = 0.5  # gradient norm clip of each policy
    critic_weight_decay: float = 1e-3  # Adam weight decay of the critic
    attention_regulariser: float = 1e-3  # weight of the attention-logit penalty
    policy_regulariser: float = 1e-3  # weight of the policy-logit penalty
    normalise_rewards: bool = True  # rewards normalised by the buffer's per-robot mean, std
    # discrete actions: box9 ({-1, 0, 1}^2, the continuous box's reach) or mpe5 (the MPE's 5)
    action_set: str = DEFAULT_DISCRETE_ACTION_SET

    def __post_init__(self) -> None:
        owner = "MAACConfig"
        check_hidden(owner, "policy_hidden", self.policy_hidden)
        check_positive_int(owner, "critic_hidden", self.critic_hidden)
        check_positive_int(owner, "attention_heads", self.attention_heads)
        if self.critic_hidden % self.attention_heads:
            raise ValueError(
                f"{owner}.attention_heads must divide critic_hidden ({self.critic_hidden}), "
                f"got {self.attention_heads!r}"
            )
        check_finite(owner, "policy_lr", self.policy_lr)
        check_finite(owner, "critic_lr", self.critic_lr)
        check_finite(owner, "gamma", self.gamma, low=0.0, low_open=False, high=1.0, high_open=True)
        check_finite(owner, "tau", self.tau, high=1.0)
        check_finite(owner, "reward_scale", self.reward_scale)
        check_positive_int(owner, "batch_size", self.batch_size)
        check_positive_int(owner, "buffer_size", self.buffer_size)
        check_positive_int(owner, "update_every", self.update_every)
        check_positive_int(owner, "gradient_steps", self.gradient_steps)
        check_finite(owner, "critic_grad_clip_factor", self.critic_grad_clip_factor)
        check_finite(owner, "policy_grad_clip", self.policy_grad_clip)
        check_finite(owner, "critic_weight_decay", self.critic_weight_decay, low_open=False)
        check_finite(owner, "attention_regulariser", self.attention_regulariser, low_open=False)
        check_finite(owner, "policy_regulariser", self.policy_regulariser, low_open=False)
        if not isinstance(self.normalise_rewards, bool):
            raise ValueError(
                f"{owner}.normalise_rewards must be a bool, got {self.normalise_rewards!r}"
            )
        check_choice(owner, "action_set", self.action_set, DISCRETE_ACTION_SETS)

    @property
    def num_actions(self) -> int:
        """How many discrete actions each policy chooses among."""
        return len(DISCRETE_ACTION_SETS[self.action_set])

    @property
    def head_dim(self) -> int:
        return self.critic_hidden // self.attention_heads


@struct.dataclass
class MAACState:
    """Parameters, their targets and optimiser states.

    ``policy``: stacked on a leading robot axis. ``critic``: a dict with the per-robot
    (stacked) ``encoder``, ``state_encoder`` and ``head``, and the shared ``attention``.
    """

    policy: Any
    critic: Any
    target_policy: Any
    target_critic: Any
    policy_opt: Any
    critic_opt: Any


class MAAC:
    """MAAC for ``N`` robots with discrete actions; see the module docstring."""

    name = "maac"
    discrete = True

    def __init__(self, config: MAACConfig = MAACConfig()) -> None:
        self.config = config
        # The training loop normalises rewards by the buffer's statistics when asked.
        self.needs_reward_stats = config.normalise_rewards
        hidden = config.critic_hidden
        self.num_actions = config.num_actions
        self.policy_net = MLP(config.policy_hidden, self.num_actions, leaky)
        self.encoder = nn.Dense(hidden)
        self.state_encoder = nn.Dense(hidden)
        self.head = MLP((hidden,), self.num_actions, leaky)
        self.policy_optimiser = optax.adam(config.policy_lr)
        self.critic_optimiser = optax.chain(
            optax.add_decayed_weights(config.critic_weight_decay),  # L2 into the gradient
            optax.adam(config.critic_lr),
        )

    # ------------------------------------------------------------ parameters
    def param_shapes(self, num_robots: int, obs_size: int) -> dict:
        """Shapes of every parameter: ``policy`` and ``critic`` (see :class:`MAACState`)."""
        hidden = self.config.critic_hidden
        return {
            "policy": per_robot_shapes(self.policy_net, num_robots, obs_size),
            "critic": {
                "encoder": per_robot_shapes(self.encoder, num_robots, obs_size + self.num_actions),
                "state_encoder": per_robot_shapes(self.state_encoder, num_robots, obs_size),
                "head": per_robot_shapes(self.head, num_robots, 2 * hidden),
                # Shared by all robots; all heads side by side, head h in columns
                # h d .. (h + 1) d.
                "attention": {
                    "key": (hidden, hidden),
                    "query": (hidden, hidden),
                    "value": (hidden, hidden),
                    "value_bias": (hidden,),
                },
            },
        }

    def init(self, key: jax.Array, num_robots: int, obs_size: int) -> MAACState:
        if num_robots < 2:
            raise ValueError(f"MAAC needs at least 2 robots to attend over, got {num_robots}")
        params = lecun_init(key, self.param_shapes(num_robots, obs_size))
        policy, critic = params["policy"], params["critic"]
        return MAACState(
            policy=policy,
            critic=critic,
            target_policy=policy,
            target_critic=critic,
            policy_opt=self.policy_optimiser.init(policy),
            critic_opt=self.critic_optimiser.init(critic),
        )

    # ------------------------------------------------------------ networks
    def policy_logits(self, policy_params: Any, obs: jax.Array) -> jax.Array:
        """Logits of every robot's policy, ``[B, N, A]``."""
        return apply_per_robot(self.policy_net, policy_params, obs)

    def encode(
        self, critic_params: dict, obs: jax.Array, action: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """``e_j = leaky(f_j(o_j, onehot(a_j)))`` and ``s_i = leaky(g_i(o_i))``, ``[B, N, D]``."""
        onehot = jax.nn.one_hot(action, self.num_actions, dtype=obs.dtype)
        e = leaky(
            apply_per_robot(self.encoder, critic_params["encoder"], jnp.concatenate(
                [obs, onehot], axis=-1
            ))
        )
        s = leaky(apply_per_robot(self.state_encoder, critic_params["state_encoder"], obs))
        return e, s

    def critic_values(
        self, critic_params: dict, obs: jax.Array, action: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """``Q_i(o, (a, a_-i))`` for every action ``a`` of every robot, ``[B, N, A]``,
        with the attention weights and logits of :func:`attend`."""
        e, s = self.encode(critic_params, obs, action)
        x, weights, logits = attend(critic_params["attention"], e, s, self.config.attention_heads)
        all_q = apply_per_robot(self.head, critic_params["head"], jnp.concatenate([s, x], -1))
        return all_q, weights, logits

    def q_values(self, critic_params: dict, obs: jax.Array, action: jax.Array) -> jax.Array:
        """``Q_i(o, a)``, ``[B, N]``."""
        return select(self.critic_values(critic_params, obs, action)[0], action)

    # ------------------------------------------------------------ interface
    def act(self, state: MAACState, obs: jax.Array, key: jax.Array, explore: bool) -> jax.Array:
        """Samples each robot's categorical policy (``explore``) or takes its argmax."""
        logits = self.policy_logits(state.policy, obs)
        if explore:
            return jax.random.categorical(key, logits, axis=-1).astype(jnp.int32)
        return jnp.argmax(logits, axis=-1).astype(jnp.int32)

    def normalise_rewards(self, batch: Transition, mean: jax.Array, std: jax.Array) -> Transition:
        """``(r_i - mean_i) / std_i`` per robot, ``std`` floored at 1e-6.

        The training loop passes the replay buffer's per-robot statistics of every reward
        added so far; the original uses those of the rewards its buffer holds (the same
        until the buffer wraps around) and divides by the population standard deviation
        with no floor.
        """
        reward = (batch.reward - mean[None, :]) / jnp.maximum(std, REWARD_STD_EPS)[None, :]
        return batch.replace(reward=reward)

    def td_target(self, state: MAACState, batch: Transition, gumbel: jax.Array) -> jax.Array:
        """``y_i = r_i + gamma (1 - done) Q'_i(o', a') - log pi'_i(a'_i | o'_i) / reward_scale``
        with ``a' ~ pi'(. | o')`` sampled with the Gumbel noise ``gumbel`` ``[B, N, A]``
        (:func:`sample_actions`); ``[B, N]``."""
        c = self.config
        next_action, next_log_pi = sample_actions(
            self.policy_logits(state.target_policy, batch.next_obs), gumbel
        )
        next_q = self.q_values(state.target_critic, batch.next_obs, next_action)
        return (
            batch.reward
            + c.gamma * (1.0 - batch.done)[:, None] * next_q
            - next_log_pi / c.reward_scale
        )

    def scale_shared_grads(self, grads: dict, num_robots: int) -> dict:
        """Divides the gradients of :data:`SHARED_CRITIC_MODULES` by ``N``."""
        return {
            name: jax.tree_util.tree_map(lambda g: g / num_robots, value)
            if name in SHARED_CRITIC_MODULES
            else value
            for name, value in grads.items()
        }

    def update(self, state: MAACState, batch: Transition, key: jax.Array):
        """One gradient step of the critic, then of the policies, then the targets."""
        c = self.config
        num_robots = batch.reward.shape[1]
        # One draw of Gumbel noise samples both the target policies' next actions and the
        # current policies' actions (one random-number kernel per update).
        gumbel = jax.random.gumbel(key, (2, *batch.reward.shape, self.num_actions))
        target = jax.lax.stop_gradient(self.td_target(state, batch, gumbel[0]))

        def critic_loss(params):
            all_q, weights, logits = self.critic_values(params, batch.obs, batch.action)
            q = select(all_q, batch.action)
            mse = jnp.mean((q - target) ** 2, axis=0)  # [N]
            penalty = c.attention_regulariser * attention_logit_penalty(logits)
            return jnp.sum(mse + penalty), (jnp.mean(mse), q, weights)

        (_, (mse, q, weights)), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(
            state.critic
        )
        c_grads = self.scale_shared_grads(c_grads, num_robots)
        c_grads, _ = optax.clip_by_global_norm(c.critic_grad_clip_factor * num_robots).update(
            c_grads, optax.EmptyState()
        )
        c_updates, critic_opt = self.critic_optimiser.update(
            c_grads, state.critic_opt, state.critic
        )
        critic = optax.apply_updates(state.critic, c_updates)

        def policy_loss(params):
            logits = self.policy_logits(params, batch.obs)
            log_probs = jax.nn.log_softmax(logits, axis=-1)
            action, log_pi = sample_actions(logits, gumbel[1])
            all_q, _, _ = self.critic_values(critic, batch.obs, action)
            advantage = select(all_q, action) - baseline(all_q, jnp.exp(log_probs))
            bracket = jax.lax.stop_gradient(log_pi / c.reward_scale - advantage)
            per_robot = jnp.mean(log_pi * bracket, axis=0) + c.policy_regulariser * jnp.mean(
                logits**2, axis=(0, 2)
            )
            entropy = -jnp.sum(jnp.exp(log_probs) * log_probs, axis=-1)
            return jnp.sum(per_robot), (jnp.mean(per_robot), jnp.mean(entropy))

        (_, (p_loss, entropy)), p_grads = jax.value_and_grad(policy_loss, has_aux=True)(
            state.policy
        )
        p_grads = clip_by_global_norm_per_robot(p_grads, c.policy_grad_clip)
        p_updates, policy_opt = self.policy_optimiser.update(p_grads, state.policy_opt)
        policy = optax.apply_updates(state.policy, p_updates)

        new_state = MAACState(
            policy=policy,
            critic=critic,
            target_policy=soft_update(state.target_policy, policy, c.tau),
            target_critic=soft_update(state.target_critic, critic, c.tau),
            policy_opt=policy_opt,
            critic_opt=critic_opt,
        )
        metrics = {
            "critic_loss": mse,
            "policy_loss": p_loss,
            "q_mean": jnp.mean(q),
            "entropy": entropy,
            "attention_max": jnp.mean(jnp.max(weights, axis=2)),
        }
        return new_state, metrics

    def flops_per_update(self, num_robots: int, obs_size: int) -> float:
        """Matrix-multiply FLOPs of one update: forward 1x, backward 2x per network pass.

        Per robot and sample, a policy pass costs ``P = 2 (F h_1 + h_1 h_2 + A h_2)`` and
        a critic pass ``C = 2 D (F + A) + 2 D F`` (encoders) ``+ 3 * 2 D^2`` (keys,
        queries, values of all heads) ``+ 2 * 2 N D`` (logits and weighted values over
        all ``N`` robots, the masked one included) ``+ 2 (2 D D + A D)`` (head), for ``A``
        actions. One update:
        target policy and target critic forward (``P + C``), critic loss forward and
        backward (``3 C``), policy loss forward and backward (``3 P``) with a forward
        pass of the updated critic (``C``): ``4 P + 5 C``, times batch and robots.
        """
        c = self.config
        d = c.critic_hidden
        actions = self.num_actions
        policy = mlp_flops([obs_size, *c.policy_hidden, actions])
        critic = (
            2 * d * (obs_size + actions)
            + 2 * d * obs_size
            + 3 * 2 * d * d
            + 2 * 2 * num_robots * d
            + mlp_flops([2 * d, d, actions])
        )
        per_sample = 4 * policy + 5 * critic
        return float(np.float64(per_sample) * c.batch_size * num_robots)
