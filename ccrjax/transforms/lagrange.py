"""The Lagrange multiplier of a cost constraint, by gradient ascent or by PID control.

A constrained MDP maximises the return subject to the expected cost ``J_c`` staying at or
below a limit ``d``; the Lagrangian ``J_r - lambda_c (J_c - d)`` is maximised over the
policy and minimised over ``lambda_c >= 0``. Gradient ascent on ``lambda_c`` adds ``lr (J_c
- d)`` after each measurement and projects onto ``[0, cap]``; its multiplier integrates the
error, so it overshoots and oscillates when the cost answers with a delay. Stooke, Achiam
and Abbeel (*Responsive Safety in Reinforcement Learning by PID Lagrangian Methods*, ICML
2020) control the multiplier with a PID controller instead, of which gradient ascent is the
integral-only case (``kp = kd = 0``, ``ki = lr``):

    e_k     = J_c,k - d                                   (cost_error)
    I_k     = min(cap, max(0, I_{k-1} + ki e_k))          (integral_update)
    P_k     = a_p P_{k-1} + (1 - a_p) e_k                 (ema: a smoothed error)
    C_k     = a_d C_{k-1} + (1 - a_d) J_c,k               (ema: a smoothed cost)
    D_k     = max(0, C_k - C_{k-delay})                   (derivative_term: rises only)
    lambda_k = min(cap, max(0, kp P_k + I_k + kd D_k))    (pid_multiplier)

with ``I_0`` the multiplier's initial value and ``C`` before the first measurement 0. The
cap keeps an early multiplier, measured while the policy is still random, from growing
without bound; it bounds the integral too (anti-windup: a multiplier held at the cap starts
down as soon as the cost is below the limit, where OmniSafe's integral keeps growing). The
arithmetic otherwise follows OmniSafe's ``PIDLagrangian`` (``docs/references.md``);
every number is an array, so one compiled program runs several limits and gains side by
side under ``jax.vmap``. ``tests/test_lagrange.py`` checks these functions against a plain
Python transcription of the equations above.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

# The controller's numbers, run parameters like CCR's lambda (defaults: integral only, that
# is gradient ascent with learning rate ``ki``; no smoothing).
DEFAULT_GAINS = {"kp": 0.0, "ki": 0.01, "kd": 0.0, "ema_p": 0.0, "ema_d": 0.0,
                 "cap": 100.0, "initial": 0.0}


@struct.dataclass
class MultiplierState:
    """What the controller keeps between measurements (a fixed structure)."""

    multiplier: jax.Array  # lambda_c in force, in [0, cap]
    integral: jax.Array  # I, >= 0
    error_ema: jax.Array  # P: the smoothed cost error
    cost_ema: jax.Array  # C: the smoothed cost
    cost_history: jax.Array  # [delay] the last ``delay`` values of C, a ring
    updates: jax.Array  # int32: measurements so far (the ring's position)


def init_multiplier(initial: jax.Array | float, delay: int) -> MultiplierState:
    """The state before any measurement: ``lambda_c = I = initial`` (>= 0); ``delay``, the
    derivative's lag in measurements (a static size, at least 1)."""
    if delay < 1:
        raise ValueError(f"delay must be >= 1 measurement, got {delay}")
    initial = jnp.maximum(jnp.asarray(initial, jnp.float32), 0.0)
    zero = jnp.zeros((), jnp.float32)
    return MultiplierState(multiplier=initial, integral=initial, error_ema=zero, cost_ema=zero,
                           cost_history=jnp.zeros((delay,), jnp.float32),
                           updates=jnp.zeros((), jnp.int32))


def cost_error(cost: jax.Array, limit: jax.Array) -> jax.Array:
    """``e = J_c - d``: positive while the constraint is violated."""
    return cost - limit


def integral_update(integral: jax.Array, error: jax.Array, ki: jax.Array,
                    cap: jax.Array) -> jax.Array:
    """``I <- min(cap, max(0, I + ki e))``: projected gradient ascent on the multiplier."""
    return jnp.clip(integral + ki * error, 0.0, cap)


def ema(previous: jax.Array, value: jax.Array, alpha: jax.Array) -> jax.Array:
    """``alpha previous + (1 - alpha) value`` (``alpha = 0``: the value itself)."""
    return alpha * previous + (1.0 - alpha) * value


def derivative_term(cost_ema: jax.Array, cost_delayed: jax.Array) -> jax.Array:
    """``D = max(0, C_k - C_{k-delay})``: a rising cost raises the multiplier at once, a
    falling one does not lower it (Stooke et al.'s one-sided derivative)."""
    return jnp.maximum(cost_ema - cost_delayed, 0.0)


def pid_multiplier(state: MultiplierState, cost: jax.Array, limit: jax.Array,
                   gains: dict[str, jax.Array]) -> MultiplierState:
    """One measurement ``cost`` (the constrained quantity, e.g. the dangerous-step
    frequency of the last training episodes) against ``limit``: the controller's new state
    and ``lambda_c = min(cap, max(0, kp P + I + kd D))``."""
    chex.assert_rank([cost, limit], 0)
    error = cost_error(cost, limit)
    integral = integral_update(state.integral, error, gains["ki"], gains["cap"])
    error_ema = ema(state.error_ema, error, gains["ema_p"])
    cost_ema = ema(state.cost_ema, cost, gains["ema_d"])
    slot = state.updates % state.cost_history.shape[0]
    derivative = derivative_term(cost_ema, state.cost_history[slot])
    raw = gains["kp"] * error_ema + integral + gains["kd"] * derivative
    return MultiplierState(
        multiplier=jnp.clip(raw, 0.0, gains["cap"]), integral=integral, error_ema=error_ema,
        cost_ema=cost_ema, cost_history=state.cost_history.at[slot].set(cost_ema),
        updates=state.updates + 1)


def ascent_multiplier(state: MultiplierState, cost: jax.Array, limit: jax.Array,
                      lr: jax.Array, cap: jax.Array) -> MultiplierState:
    """Projected gradient ascent, ``lambda_c <- min(cap, max(0, lambda_c + lr (J_c - d)))``:
    the PID controller with ``kp = kd = 0`` and ``ki = lr``."""
    gains = {"kp": 0.0, "ki": lr, "kd": 0.0, "ema_p": 0.0, "ema_d": 0.0, "cap": cap}
    return pid_multiplier(state, cost, limit, gains)


__all__ = [
    "DEFAULT_GAINS", "MultiplierState", "ascent_multiplier", "cost_error", "derivative_term",
    "ema", "init_multiplier", "integral_update", "pid_multiplier",
]
