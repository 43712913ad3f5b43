"""CCR's learned physical model: polynomial dynamics with learnable coefficients.

The paper's model ``s_hat_t = M(s_{t-1}, a_{t-1})`` is "a group of polynomial
dynamics functions with learnable coefficients". Here it predicts robot ``i``'s
own state ``s_t = (p_t, v_t)`` (position and velocity, 4 numbers):

* inputs ``x = (v_{t-1}, u_{t-1})`` (4 numbers): the previous velocity and the
  control command ``u in [-1, 1]^2``; for discrete actions ``u`` is the action's
  command in ``{-1, 0, 1}^2`` (:data:`ccrjax.envs.world.DISCRETE_ACTION_SETS`), never scaled
  by a simulator constant (the model learns the gain itself);
* outputs ``y = (p_t - p_{t-1}, v_t)``; the prediction is
  ``p_hat_t = p_{t-1} + y_hat[0:2]``, ``v_hat_t = y_hat[2:4]``;
* ``y_hat = C^T phi(x)``, ``phi(x)`` all monomials of ``x`` of total degree
  ``<= degree`` (constant included: ``binom(4 + degree, degree)`` features, 15 at
  degree 2), ``C`` a ``[P, 4]`` coefficient matrix shared by all robots (the team is
  homogeneous, so every robot's transitions train the same model).

Why not more inputs or outputs:

* **absolute position is not an input.** Particle physics is translation
  invariant, so it carries no information about nominal motion. Hazards are
  drawn in a fixed box across the way; with ``p`` among the inputs the model
  could partly learn "around x = 0 robots get pushed" and predict the hazard,
  which is exactly the surprise CCR wants to measure;
* **relative features are not predicted.** The distances and directions to the
  other robots depend on those robots' actions, which robot ``i`` does not know;
  the destination features are functions of the own position, so predicting
  them adds no information beyond ``p_t``.

Fit: closed-form weighted ridge regression, the normal equations

    (A + ridge * diag(A)) C = B,  A = mean_w[phi phi^T] ([P, P]),  B = mean_w[phi y^T] ([P, 4])

from sufficient statistics accumulated over every transition (:func:`accumulate`)
and solved at every episode start (:func:`fit`). The statistics are *weighted
means* (not sums), updated as ``S <- S + (sum_batch w s - w_batch S) / W_new``,
so their magnitudes stay of order one however long training runs in float32.
The ridge is relative to each feature's own second moment (the system is solved
after scaling by ``sqrt(diag(A))``), which also keeps float32 conditioning sane.

Robust weights (iteratively reweighted least squares across episodes): each
transition enters with weight ``w = min(1, tolerance / e)``, ``e`` its squared
prediction error under the *current* coefficients. Nominal motion, which the
model predicts well, gets weight 1; hazard pushes and robot-robot contacts,
which it cannot predict, get a tiny weight, so they do not bend the model
towards themselves and stay visible as large errors. Before the first fit
(coefficients zero) ``e = |y|^2`` and every transition still counts with a
positive weight. The model never reads the simulator's hazard code or constants.

Why a closed form: it is exact for the accumulated statistics and has no learning
rate, where a gradient method would need many steps per fit and a learning rate, and
never be exact. The fit is a ``P x P``
Cholesky solve with 4 right-hand sides, once per episode; the per-step cost is
:func:`accumulate`'s.
"""

from __future__ import annotations

import functools
import itertools
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ccrjax.envs.world import DEFAULT_DISCRETE_ACTION_SET, discrete_command

NUM_INPUTS = 4  # (v_x, v_y, u_x, u_y)
NUM_OUTPUTS = 4  # (dp_x, dp_y, v_x, v_y)
MIN_DEGREE, MAX_DEGREE = 1, 5


@functools.cache
def monomial_plan(degree: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Static index lists that build all monomials of the 4 inputs up to ``degree``.

    Monomials are listed by degree, then lexicographically by their sorted
    variable indices ``(i_1 <= ... <= i_d)``. A monomial of degree ``d`` is its
    parent ``(i_1 .. i_{d-1})`` (degree ``d - 1``) times input ``i_d``. For each
    degree ``d >= 1`` the plan holds ``(parent, last)``: indices of the parents in
    the list so far, and the input each is multiplied by.
    """
    if not MIN_DEGREE <= degree <= MAX_DEGREE:
        raise ValueError(f"degree must be an integer in [{MIN_DEGREE}, {MAX_DEGREE}], got {degree}")
    position = {(): 0}
    plan = []
    for d in range(1, degree + 1):
        parents, lasts = [], []
        for combo in itertools.combinations_with_replacement(range(NUM_INPUTS), d):
            parents.append(position[combo[:-1]])
            lasts.append(combo[-1])
        for combo in itertools.combinations_with_replacement(range(NUM_INPUTS), d):
            position[combo] = len(position)
        plan.append((np.array(parents, np.int32), np.array(lasts, np.int32)))
    return tuple(plan)


def num_features(degree: int) -> int:
    """``P = binom(4 + degree, degree)``: monomials of 4 inputs of total degree <= degree."""
    return math.comb(NUM_INPUTS + degree, degree)


def polynomial_features(inputs: jax.Array, degree: int) -> jax.Array:
    """``phi(x)``: every monomial of ``x`` up to total ``degree``, along axis 1.

    Args:
      inputs: ``float[N, 4, E]`` (robots, inputs ``x``, environments).
      degree: maximum total degree, 1 to 5.

    Returns:
      ``float32[N, P, E]``; feature 0 is the constant 1, features 1..4 are ``x``.
    """
    chex.assert_rank(inputs, 3)
    chex.assert_axis_dimension(inputs, 1, NUM_INPUTS)
    inputs = inputs.astype(jnp.float32)
    features = jnp.ones_like(inputs[:, :1])
    for parents, lasts in monomial_plan(degree):
        features = jnp.concatenate([features, features[:, parents] * inputs[:, lasts]], axis=1)
    return features


def command_vector(action: jax.Array, discrete: bool,
                   action_set: str = DEFAULT_DISCRETE_ACTION_SET) -> jax.Array:
    """The control command ``u`` of every robot, ``float32[N, 2, E]``.

    Continuous actions (``float[N, 2, E]``) are clipped to ``[-1, 1]`` as the
    simulator does; discrete ones (``int[N, E]``) become their command in
    ``action_set`` (:func:`ccrjax.envs.world.discrete_command`).
    """
    if discrete:
        return discrete_command(action, action_set)
    chex.assert_rank(action, 3)
    return jnp.clip(action.astype(jnp.float32), -1.0, 1.0)


def model_inputs(own_state: jax.Array, command: jax.Array) -> jax.Array:
    """``x = (v_{t-1}, u_{t-1})``, ``float32[N, 4, E]``, from the own state ``(p, v)`` ``[N, 4, E]``
    and the command ``[N, 2, E]``."""
    chex.assert_rank([own_state, command], 3)
    chex.assert_axis_dimension(own_state, 1, 4)
    chex.assert_axis_dimension(command, 1, 2)
    return jnp.concatenate([own_state[:, 2:4], command], axis=1).astype(jnp.float32)


def model_targets(own_state: jax.Array, next_own_state: jax.Array) -> jax.Array:
    """``y = (p_t - p_{t-1}, v_t)``, ``float32[N, 4, E]``, from the own states ``s_{t-1}, s_t``."""
    chex.assert_equal_shape([own_state, next_own_state])
    return jnp.concatenate(
        [next_own_state[:, 0:2] - own_state[:, 0:2], next_own_state[:, 2:4]], axis=1
    )


@struct.dataclass
class DynamicsStatistics:
    """Weighted running means of the normal equations' terms (independent of ``E``).

    ``feature_moment``: ``A = sum w phi phi^T / W`` ``[P, P]``;
    ``target_moment``: ``B = sum w phi y^T / W`` ``[P, 4]``;
    ``total_weight``: ``W = sum w`` ``[]``.
    """

    feature_moment: jax.Array
    target_moment: jax.Array
    total_weight: jax.Array


def init_statistics(degree: int) -> DynamicsStatistics:
    """No data yet: zero moments and weight."""
    p = num_features(degree)
    return DynamicsStatistics(
        feature_moment=jnp.zeros((p, p), jnp.float32),
        target_moment=jnp.zeros((p, NUM_OUTPUTS), jnp.float32),
        total_weight=jnp.zeros((), jnp.float32),
    )


def init_coefficients(degree: int) -> jax.Array:
    """``C = 0`` ``[P, 4]``: the model before its first fit."""
    return jnp.zeros((num_features(degree), NUM_OUTPUTS), jnp.float32)


def predict_targets(coefficients: jax.Array, inputs: jax.Array) -> jax.Array:
    """``y_hat = C^T phi(x)``, ``float32[N, 4, E]``, for inputs ``x`` ``[N, 4, E]``."""
    degree = _degree_of(coefficients)
    features = polynomial_features(inputs, degree)
    return jnp.einsum("npe,pk->nke", features, coefficients)


def predict_state(coefficients: jax.Array, own_state: jax.Array, command: jax.Array) -> jax.Array:
    """``s_hat_t = (p_{t-1} + dp_hat, v_hat)``, ``float32[N, 4, E]``, from ``s_{t-1}, u_{t-1}``."""
    predicted = predict_targets(coefficients, model_inputs(own_state, command))
    return jnp.concatenate([own_state[:, 0:2] + predicted[:, 0:2], predicted[:, 2:4]], axis=1)


def squared_error(coefficients: jax.Array, inputs: jax.Array, targets: jax.Array) -> jax.Array:
    """``e = |y_hat - y|^2`` per robot and environment, ``float32[N, E]``."""
    chex.assert_equal_shape([inputs, targets])
    residual = predict_targets(coefficients, inputs) - targets
    return jnp.sum(residual * residual, axis=1)


def robust_weight(error: jax.Array, tolerance: float) -> jax.Array:
    """``w = min(1, tolerance / e)`` (1 where ``e <= tolerance``; 0 where ``e`` is not finite)."""
    weight = tolerance / jnp.maximum(error, tolerance)
    return jnp.where(jnp.isfinite(error), weight, 0.0)


def accumulate(
    statistics: DynamicsStatistics,
    coefficients: jax.Array,
    inputs: jax.Array,
    targets: jax.Array,
    tolerance: float,
) -> DynamicsStatistics:
    """Adds a batch of transitions ``(x, y)`` ``[N, 4, E]`` with robust weights.

    Every transition gets ``w = min(1, tolerance / e)`` under ``coefficients``; the
    running means move as ``S <- S + (sum w s - (sum w) S) / (W + sum w)``.
    """
    chex.assert_equal_shape([inputs, targets])
    features = polynomial_features(inputs, _degree_of(coefficients))  # [N, P, E]
    residual = jnp.einsum("npe,pk->nke", features, coefficients) - targets
    return accumulate_features(
        statistics, features, targets, jnp.sum(residual * residual, axis=1), tolerance
    )


def accumulate_features(
    statistics: DynamicsStatistics,
    features: jax.Array,
    targets: jax.Array,
    error: jax.Array,
    tolerance: float,
) -> DynamicsStatistics:
    """:func:`accumulate` for callers that already hold ``phi(x)`` ``[N, P, E]`` and each
    transition's squared error ``e`` ``[N, E]`` under the current coefficients (CCR's
    transform computes both for the emergency score, so the step computes them once)."""
    chex.assert_rank([features, targets, error], [3, 3, 2])
    weight = robust_weight(error, tolerance)  # [N, E]
    # A non-finite transition has weight 0; zero its values too, since 0 * nan is nan.
    valid = (weight > 0)[:, None]
    features = jnp.where(valid, features, 0.0)
    targets = jnp.where(valid, targets, 0.0)
    weighted = features * weight[:, None]
    batch_feature_sum = jnp.einsum("npe,nqe->pq", weighted, features)
    batch_target_sum = jnp.einsum("npe,nke->pk", weighted, targets)
    batch_weight = jnp.sum(weight)
    total_weight = statistics.total_weight + batch_weight
    step = jnp.where(total_weight > 0, 1.0 / jnp.where(total_weight > 0, total_weight, 1.0), 0.0)
    return DynamicsStatistics(
        feature_moment=statistics.feature_moment
        + (batch_feature_sum - batch_weight * statistics.feature_moment) * step,
        target_moment=statistics.target_moment
        + (batch_target_sum - batch_weight * statistics.target_moment) * step,
        total_weight=total_weight,
    )


def fit(statistics: DynamicsStatistics, ridge: float) -> jax.Array:
    """The ridge solution ``C = (A + ridge diag(A))^{-1} B``, ``float32[P, 4]``.

    Solved in the scaled basis ``phi / sqrt(A_pp)`` (features no data excited keep
    scale 1) by Cholesky. With no data (``A = B = 0``) it gives ``C = 0``.
    """
    feature_moment = statistics.feature_moment
    p = feature_moment.shape[0]
    chex.assert_shape(feature_moment, (p, p))
    chex.assert_shape(statistics.target_moment, (p, NUM_OUTPUTS))
    diagonal = jnp.diagonal(feature_moment)
    scale = jnp.where(diagonal > 0, jnp.sqrt(jnp.where(diagonal > 0, diagonal, 1.0)), 1.0)
    scaled = feature_moment / (scale[:, None] * scale[None, :])
    regularised = scaled + ridge * jnp.eye(p, dtype=scaled.dtype)
    factor = jax.scipy.linalg.cho_factor(regularised, lower=True)
    solution = jax.scipy.linalg.cho_solve(factor, statistics.target_moment / scale[:, None])
    return solution / scale[:, None]


def _degree_of(coefficients: jax.Array) -> int:
    p = coefficients.shape[0]
    for degree in range(MIN_DEGREE, MAX_DEGREE + 1):
        if num_features(degree) == p:
            return degree
    raise ValueError(f"coefficients must have binom(4 + d, d) rows for d in 1..5, got {p}")
