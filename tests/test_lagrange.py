"""The Lagrange multiplier's controllers (:mod:`ccrjax.transforms.lagrange`): equal to a
plain Python transcription of the equations, gradient ascent as the integral-only PID,
bounds, several limits at once under vmap, and the reason for PID: less overshoot on a
cost that answers the multiplier with a delay."""

from __future__ import annotations

from collections import deque

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccrjax.transforms import lagrange

DELAY = 3


def reference(costs, limit, gains, delay=DELAY) -> list[float]:
    """The module docstring's equations, one measurement at a time, in plain Python."""
    integral, error_ema, cost_ema = max(gains["initial"], 0.0), 0.0, 0.0
    past = deque([0.0] * delay, maxlen=delay)
    out = []
    for cost in costs:
        error = cost - limit
        integral = min(gains["cap"], max(0.0, integral + gains["ki"] * error))
        error_ema = gains["ema_p"] * error_ema + (1 - gains["ema_p"]) * error
        cost_ema = gains["ema_d"] * cost_ema + (1 - gains["ema_d"]) * cost
        derivative = max(0.0, cost_ema - past[0])
        past.append(cost_ema)
        raw = gains["kp"] * error_ema + integral + gains["kd"] * derivative
        out.append(min(gains["cap"], max(0.0, raw)))
    return out


def run(costs, limit, gains, delay=DELAY) -> np.ndarray:
    def step(state, cost):
        state = lagrange.pid_multiplier(state, cost, limit, gains)
        return state, state.multiplier

    state = lagrange.init_multiplier(gains["initial"], delay)
    _, multipliers = jax.lax.scan(step, state, jnp.asarray(costs, jnp.float32))
    return np.asarray(multipliers)


GAINS = [
    dict(lagrange.DEFAULT_GAINS),
    {"kp": 0.5, "ki": 0.05, "kd": 2.0, "ema_p": 0.9, "ema_d": 0.5, "cap": 3.0, "initial": 0.2},
    {"kp": 2.0, "ki": 0.5, "kd": 0.0, "ema_p": 0.0, "ema_d": 0.95, "cap": 1.0, "initial": 0.0},
]


@pytest.mark.parametrize("gains", GAINS)
def test_the_controller_is_its_equations(gains):
    costs = np.random.default_rng(0).uniform(0.0, 0.6, size=40)
    costs[10:14] = 2.0  # a burst that drives the multiplier to its cap for some gains
    np.testing.assert_allclose(run(costs, 0.25, gains), reference(costs, 0.25, gains),
                               rtol=1e-5, atol=1e-6)


def test_gradient_ascent_is_the_integral_only_controller():
    """``lambda <- min(cap, max(0, lambda + lr (J_c - d)))``, step by step, by hand."""
    costs = [0.5, 0.5, 0.0, 0.0, 0.0, 0.9]
    state = lagrange.init_multiplier(0.0, 1)
    seen = []
    for cost in costs:
        state = lagrange.ascent_multiplier(state, jnp.float32(cost), jnp.float32(0.2),
                                           jnp.float32(1.0), jnp.float32(0.5))
        seen.append(float(state.multiplier))
    np.testing.assert_allclose(seen, [0.3, 0.5, 0.3, 0.1, 0.0, 0.5], atol=1e-6)


def test_the_multiplier_stays_within_zero_and_the_cap_and_unwinds():
    gains = {**lagrange.DEFAULT_GAINS, "ki": 10.0, "cap": 2.0}
    high = run([1.0] * 20 + [0.0], 0.1, gains)
    assert high.min() >= 0.0 and high.max() == pytest.approx(2.0)
    assert high[-1] == pytest.approx(1.0)  # one step below the limit: 2 - 10 x 0.1
    low = run([0.0] * 10, 0.1, {**gains, "initial": 1.0})
    assert low[-1] == 0.0 and (np.diff(low) <= 0).all()
    # With the proportional term the raw value exceeds the cap: the multiplier stops there.
    pid = run([1.0] * 20, 0.1, {**gains, "kp": 1.0, "ema_p": 0.5})
    assert pid.max() == pytest.approx(2.0)
    # No wind-up below 0: after a long stretch under the limit, one step above it raises
    # the multiplier at once (the integral was held at 0, not driven to -5).
    back = run([0.0] * 50 + [1.0], 0.1, {**gains, "ki": 1.0, "cap": 100.0})
    assert back[-1] == pytest.approx(0.9)


def test_several_limits_train_side_by_side_under_vmap():
    costs = jnp.linspace(0.0, 0.4, 25)
    limits = jnp.array([0.01, 0.05, 0.2, 1.0])
    gains = GAINS[1]
    together = jax.vmap(lambda limit: run_traced(costs, limit, gains))(limits)
    for row, limit in zip(np.asarray(together), np.asarray(limits), strict=True):
        np.testing.assert_allclose(row, reference(np.asarray(costs), float(limit), gains),
                                   rtol=1e-5, atol=1e-6)
    assert (np.diff(np.asarray(together)[:, -1]) <= 0).all()  # a looser limit, a smaller lambda


def run_traced(costs, limit, gains):
    def step(state, cost):
        state = lagrange.pid_multiplier(state, cost, limit, gains)
        return state, state.multiplier

    _, multipliers = jax.lax.scan(step, lagrange.init_multiplier(gains["initial"], DELAY),
                                  costs)
    return multipliers


def lagged_plant(gains, steps=300, lag=10, limit=0.1):
    """A cost that falls as the multiplier rises, answering ``lag`` measurements late:
    ``J_c = 0.5 exp(-2 lambda)``, a stand-in for a policy that learns to be safer."""
    state = lagrange.init_multiplier(gains["initial"], DELAY)
    history, costs = [0.0] * lag, []
    for _ in range(steps):
        cost = 0.5 * np.exp(-2.0 * history[-lag])
        costs.append(cost)
        state = lagrange.pid_multiplier(state, jnp.float32(cost), jnp.float32(limit), gains)
        history.append(float(state.multiplier))
    return np.array(costs)


def test_pid_control_damps_the_swing_of_gradient_ascent_on_a_lagged_cost():
    """The reason for PID (Stooke et al.): on a cost that answers late, integral-only
    control keeps swinging the cost far below the limit and back; proportional and
    derivative terms damp the swing and hold the cost at the limit."""
    ascent = {**lagrange.DEFAULT_GAINS, "ki": 1.0}
    pid = {**ascent, "kp": 1.0, "kd": 4.0}
    swings = {}
    for name, gains in (("ascent", ascent), ("pid", pid)):
        late = lagged_plant(gains)[-100:]
        swings[name] = late.max() - late.min()
    assert swings["ascent"] > 0.2 and swings["pid"] < 0.1 * swings["ascent"], swings
    assert abs(lagged_plant(pid)[-50:].mean() - 0.1) < 0.005


def test_a_delay_below_one_is_refused():
    with pytest.raises(ValueError, match="delay must be >= 1"):
        lagrange.init_multiplier(0.0, 0)
