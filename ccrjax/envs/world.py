"""Particle physics of the maintained Multi-Agent Particle Environment (MPE), batched.

Everything here is a pure function of arrays, faithful to the maintained MPE
(``mpe2``, formerly ``pettingzoo.mpe``; ``docs/references.md`` section 1):

* constants: ``dt = 0.1``, ``damping = 0.25``, ``contact_force = 100``,
  ``contact_margin = 1e-3``, mass 1, action sensitivity 5;
* the soft contact force between two discs ``a`` and ``b``::

      delta = p_a - p_b,  dist = |delta|,  dist_min = r_a + r_b
      penetration = k * softplus(-(dist - dist_min) / k),   k = contact_margin
      f_a = contact_force * delta / dist * penetration,      f_b = -f_a

* the integration order of the maintained MPE::

      p <- p + v dt;   v <- v (1 - damping);   v <- v + (F / m) dt;   clamp |v| to max_speed

Array layout
------------
All arrays are *structure of arrays* with the environment batch as the **last**
(minor) axis, because XLA on CPU vectorises along the minor axis; a step written
with ``[batch, body, 2]`` arrays, whose minor axis has length 2, ran several
times slower on our 2-core machine. For ``K`` bodies and ``B`` environments:

=============  ==================  ==========================================
array          shape               meaning
=============  ==================  ==========================================
``position``   ``float32[K, 2, B]``  body ``k``'s ``(x, y)`` in environment ``b``
``velocity``   ``float32[K, 2, B]``  body velocity
``force``      ``float32[K, 2, B]``  applied force (actions, hazards, walls)
``radius``     ``float32[K]``        disc radius of each body
=============  ==================  ==========================================

A single environment is simply ``B = 1``.

MAAC's discrete actions are ``box9`` by default, not the MPE's five
(:data:`DISCRETE_ACTION_SETS` says why). Two more deliberate differences from the MPE, both
where the MPE is undefined:
discs exactly on top of each other (``dist = 0``) get no contact force instead of
a NaN, and :func:`rectangle_stop` makes a solid axis-aligned rectangle (the hidden
obstacle, which the MPE does not have) a hard constraint on positions: the MPE's soft
contact law lets a disc at full speed about 0.35 deep into a wall before it acts.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "PhysicsParams",
    "DEFAULT_DISCRETE_ACTION_SET",
    "DISCRETE_ACTION_DIRECTIONS",
    "DISCRETE_ACTION_SETS",
    "discrete_command",
    "action_to_force",
    "contact_penetration",
    "pair_difference_matrix",
    "disc_contact_forces",
    "integrate",
    "physics_step",
    "rectangle_distance",
    "rectangle_stop",
]


@dataclasses.dataclass(frozen=True)
class PhysicsParams:
    """Constants of the particle world; defaults are the maintained MPE's."""

    dt: float = 0.1
    damping: float = 0.25
    contact_force: float = 100.0
    contact_margin: float = 1e-3
    mass: float = 1.0
    # The MPE sets no speed limit unless a scenario does; ``None`` means no clamp.
    max_speed: float | None = None

    def __post_init__(self) -> None:
        for name in ("dt", "contact_force", "contact_margin", "mass"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"PhysicsParams.{name} must be a finite number > 0, got {value!r}")
        if not (math.isfinite(self.damping) and 0.0 <= self.damping < 1.0):
            raise ValueError(f"PhysicsParams.damping must be in [0, 1), got {self.damping!r}")
        if self.max_speed is not None and not (
            math.isfinite(self.max_speed) and self.max_speed > 0
        ):
            raise ValueError(
                "PhysicsParams.max_speed must be None or a finite number > 0, "
                f"got {self.max_speed!r}"
            )


# Discrete action sets: each action is a command ``u`` in ``{-1, 0, 1}^2`` (force ``u *
# sensitivity``), action 0 doing nothing.
# * ``mpe5``: the MPE's five, {none, -x, +x, -y, +y}: one axis at a time, so the force lies
#   in the unit L1 ball where a continuous learner's lies in the box ``[-1, 1]^2``;
# * ``box9``: the box's corners, edge midpoints and centre, so a discrete learner reaches every
#   speed a continuous one does. With ``mpe5`` no robot can detour round the hidden obstacle,
#   skirt the turbulence or hold its line in the wind within the 25-step episode: the
#   reference oracle, snapped to the nearest ``mpe5`` action, succeeds in 0.3%, 20% and 4%
#   of episodes (hidden obstacle, turbulence, strong wind), snapped to ``box9`` in 99%, 99%
#   and 87%, as with continuous actions (``experiments/calibrate.py``, 1024 episodes). The
#   paper gives MAAC a discrete action space without naming it; ``box9`` is ours.
DISCRETE_ACTION_SETS: dict[str, np.ndarray] = {
    "box9": np.array(
        [[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0],
         [-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]], dtype=np.float32
    ),
    "mpe5": np.array(
        [[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]], dtype=np.float32
    ),
}
DEFAULT_DISCRETE_ACTION_SET = "box9"
DISCRETE_ACTION_DIRECTIONS = DISCRETE_ACTION_SETS[DEFAULT_DISCRETE_ACTION_SET]


def discrete_command(action: jax.Array, action_set: str = DEFAULT_DISCRETE_ACTION_SET
                     ) -> jax.Array:
    """The command ``u`` (``float32[N, 2, B]``) of discrete actions ``int[N, B]``.

    Out-of-range actions give ``u = 0``. A one-hot contraction instead of a gather: a
    gather along a non-minor axis is slow on CPU, a few fused selects are not.
    """
    chex.assert_rank(action, 2)
    directions = DISCRETE_ACTION_SETS[action_set]
    count = len(directions)
    one_hot = action[:, None, :] == jnp.arange(count, dtype=action.dtype)[None, :, None]
    ux = jnp.sum(jnp.where(one_hot, jnp.asarray(directions[:, 0])[None, :, None], 0.0), axis=1)
    uy = jnp.sum(jnp.where(one_hot, jnp.asarray(directions[:, 1])[None, :, None], 0.0), axis=1)
    return jnp.stack([ux, uy], axis=1)


def action_to_force(action: jax.Array, sensitivity: float, discrete: bool,
                    action_set: str = DEFAULT_DISCRETE_ACTION_SET) -> jax.Array:
    """Turns actions into forces, as the MPE does (``u * sensitivity``).

    Args:
      action: continuous ``float[N, 2, B]`` in ``[-1, 1]^2`` (values outside are
        clipped), or discrete ``int[N, B]``, an index into ``action_set``.
      sensitivity: the MPE's ``accel`` (5.0 by default).
      discrete: which of the two action spaces ``action`` belongs to.
      action_set: the discrete actions' set (:data:`DISCRETE_ACTION_SETS`).

    Returns:
      ``float32[N, 2, B]`` forces.
    """
    if discrete:
        return discrete_command(action, action_set) * sensitivity
    chex.assert_rank(action, 3)
    return jnp.clip(action, -1.0, 1.0).astype(jnp.float32) * sensitivity


def contact_penetration(gap: jax.Array, margin: float) -> jax.Array:
    """The MPE's smoothed penetration depth ``k * softplus(-gap / k)``, ``k = margin``.

    ``gap`` is the surface-to-surface distance (negative when overlapping).
    ``softplus(x) = max(x, 0) + log(1 + exp(-|x|))``, written out because it is
    the costliest arithmetic of a step and this form is about a third cheaper on
    CPU than ``jax.nn.softplus``; where it rounds differently (``exp(-|x|)`` below
    float32 epsilon) the force is below ``1e-8``.
    """
    x = -gap / margin
    return (jnp.maximum(x, 0.0) + jnp.log(1.0 + jnp.exp(-jnp.abs(x)))) * margin


@functools.cache
def pair_difference_matrix(num_bodies: int) -> np.ndarray:
    """``D[p, k]``: +1 if body ``k`` is the first of pair ``p``, -1 if the second.

    Pairs ``(a, b)`` with ``a < b`` in ``np.triu_indices`` order. ``D @ x`` gives
    ``x_a - x_b`` for every pair exactly (one rounding), and ``D.T @ f`` adds
    ``+f`` to ``a`` and ``-f`` to ``b``: the MPE's pairwise loop as two small
    matrix products, which on CPU ran about three times faster than the same
    contact law on a ``[K, K, B]`` all-pairs tensor.
    """
    first, second = np.triu_indices(num_bodies, 1)
    matrix = np.zeros((len(first), num_bodies), np.float32)
    matrix[np.arange(len(first)), first] = 1.0
    matrix[np.arange(len(first)), second] = -1.0
    return matrix


def disc_contact_forces(
    position: jax.Array, radius: jax.Array, params: PhysicsParams
) -> jax.Array:
    """Sum of the MPE's pairwise disc contact forces on every body.

    Args:
      position: ``float[K, 2, B]``.
      radius: ``float[K]``.
      params: physics constants.

    Returns:
      ``float32[K, 2, B]``: for body ``a``, ``sum_b contact_force * (p_a - p_b) /
      |p_a - p_b| * penetration(|p_a - p_b| - r_a - r_b)``. Coincident discs
      (distance exactly 0) exert no force on each other.
    """
    chex.assert_rank(position, 3)
    num_bodies = position.shape[0]
    chex.assert_shape(radius, (num_bodies,))
    pairs = jnp.asarray(pair_difference_matrix(num_bodies))  # [P, K]
    first, second = np.triu_indices(num_bodies, 1)
    delta = jnp.einsum("pk,kcb->pcb", pairs, position, precision="highest")  # p_a - p_b
    dist = jnp.sqrt(delta[:, 0] * delta[:, 0] + delta[:, 1] * delta[:, 1])  # [P, B]
    dist_min = (radius[first] + radius[second])[:, None]
    penetration = contact_penetration(dist - dist_min, params.contact_margin)
    separated = dist > 0.0
    scale = jnp.where(
        separated, params.contact_force * penetration / jnp.where(separated, dist, 1.0), 0.0
    )
    pair_force = scale[:, None, :] * delta  # on a; -pair_force on b
    return jnp.einsum("pk,pcb->kcb", pairs, pair_force, precision="highest")


def integrate(
    position: jax.Array, velocity: jax.Array, force: jax.Array, params: PhysicsParams
) -> tuple[jax.Array, jax.Array]:
    """The maintained MPE's integration: position first, then damped velocity.

    ``p' = p + v dt``; ``v' = v (1 - damping) + F / m dt``; then, if
    ``max_speed`` is set, ``v' <- v' / |v'| * max_speed`` where ``|v'| > max_speed``.
    """
    position = position + velocity * params.dt
    velocity = velocity * (1.0 - params.damping) + (force / params.mass) * params.dt
    if params.max_speed is not None:
        speed = jnp.sqrt(velocity[:, :1] ** 2 + velocity[:, 1:] ** 2)
        too_fast = speed > params.max_speed
        velocity = jnp.where(
            too_fast, velocity / jnp.where(too_fast, speed, 1.0) * params.max_speed, velocity
        )
    return position, velocity


def physics_step(
    position: jax.Array,
    velocity: jax.Array,
    radius: jax.Array,
    applied_force: jax.Array,
    params: PhysicsParams = PhysicsParams(),
) -> tuple[jax.Array, jax.Array]:
    """One MPE world step for ``K`` movable, colliding discs in ``B`` environments.

    Args:
      position: ``float[K, 2, B]`` positions.
      velocity: ``float[K, 2, B]`` velocities.
      radius: ``float[K]`` disc radii.
      applied_force: ``float[K, 2, B]``: actions times sensitivity plus any
        external force (hazards, walls), as the MPE's ``apply_action_force``.
      params: physics constants.

    Returns:
      ``(position, velocity)`` after one step of ``params.dt``.
    """
    chex.assert_equal_shape([position, velocity, applied_force])
    force = applied_force + disc_contact_forces(position, radius, params)
    return integrate(position, velocity, force, params)


def rectangle_distance(position: jax.Array, centre: jax.Array, half_extent: jax.Array):
    """Signed distance ``float[K, B]`` from points to an axis-aligned rectangle's boundary.

    Negative inside (minus the depth below the nearest face). The cheap half of
    :func:`rectangle_signed_distance`, for predicates that need no normal.
    (Written per component: XLA on CPU runs operations over the length-2 xy axis
    several times slower than the same arithmetic on ``[K, B]`` slices.)
    """
    rel_x = jnp.abs(position[:, 0] - centre[0][None])
    rel_y = jnp.abs(position[:, 1] - centre[1][None])
    half_x, half_y = half_extent[0][None], half_extent[1][None]
    out_x = jnp.maximum(rel_x - half_x, 0.0)
    out_y = jnp.maximum(rel_y - half_y, 0.0)
    outside = jnp.sqrt(out_x * out_x + out_y * out_y)
    return jnp.where(outside > 0.0, outside, -jnp.minimum(half_x - rel_x, half_y - rel_y))


_FAR = 1e30  # "never" for the slab times of rectangle_stop


def rectangle_stop(
    previous: jax.Array,
    position: jax.Array,
    velocity: jax.Array,
    radius: jax.Array,
    centre: jax.Array,
    half_extent: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """A solid axis-aligned rectangle as a hard constraint on discs that moved.

    The rectangle grown by each disc's radius is the region a disc's centre may not
    enter. For a disc that moved from ``previous`` (outside that region, or on its
    boundary) to ``position``, the segment between the two is tested against the
    grown rectangle (the slab method: the interval of the segment's parameter
    ``t in [0, 1]`` inside both axis slabs). A segment that enters it, however fast
    and at whatever angle (so also a disc that would tunnel through), entered
    through the face of the axis whose slab it entered last; the disc is stopped on
    that face, keeping its new coordinate along the face (it slides) but not beyond the
    face's ends (a disc that clips a corner stops at the corner, touching it), and loses
    its velocity into the face (an inelastic contact). Discs that did not enter are
    untouched. A disc thus never overlaps the rectangle (beyond float32 rounding, about
    1e-6), in any pile or corner.

    Args:
      previous: ``float[K, 2, B]`` positions before the step.
      position: ``float[K, 2, B]`` positions after the physics step.
      velocity: ``float[K, 2, B]`` velocities after the physics step.
      radius: ``float[K]`` disc radii.
      centre: ``float[2, B]`` rectangle centre per environment.
      half_extent: ``float[2, B]`` half width (x) and half height (y).

    Returns:
      ``(position, velocity)``, corrected.
    """
    r = radius[:, None]
    lows, highs, sides = [], [], []
    for axis in range(2):
        half = half_extent[axis][None] + r  # [K, B]
        start = previous[:, axis] - centre[axis][None]
        # A disc stopped on a face lies on it only up to float32 rounding (``start`` may
        # come out an ulp inside, and the disc would then count as inside the slab and
        # be thrown to another face when it slides): entry is tested against the grown
        # rectangle shrunk by a few times that rounding, so a disc may end at most that
        # deep (about 1e-6) inside it.
        half = half - 1e-6 * (1.0 + jnp.abs(centre[axis][None]) + half)
        step = position[:, axis] - previous[:, axis]
        moving = step != 0.0
        inverse = 1.0 / jnp.where(moving, step, 1.0)
        t_a = (-half - start) * inverse
        t_b = (half - start) * inverse
        in_slab = jnp.abs(start) < half
        # Large finite stand-ins for +-infinity (not moving: never entered, or always in).
        outside = jnp.where(in_slab, -_FAR, _FAR)
        lows.append(jnp.where(moving, jnp.minimum(t_a, t_b), outside))
        highs.append(jnp.where(moving, jnp.maximum(t_a, t_b), -outside))
        sides.append(jnp.where(moving, -jnp.sign(step), jnp.where(start >= 0.0, 1.0, -1.0)))
    t_enter = jnp.maximum(lows[0], lows[1])
    t_leave = jnp.minimum(highs[0], highs[1])
    hit = (t_enter < t_leave) & (t_enter < 1.0) & (t_leave > 0.0)
    through_x = lows[0] >= lows[1]
    new_position, new_velocity = [], []
    for axis, through in ((0, through_x), (1, ~through_x)):
        side = sides[axis]
        grown = half_extent[axis][None] + r
        face = centre[axis][None] + side * grown
        # Stopped on the entry face; along the face (the other axis), kept within the
        # face's ends, so a disc that clipped a corner stops at the corner, touching.
        along = jnp.clip(position[:, axis], centre[axis][None] - grown, centre[axis][None] + grown)
        new_position.append(jnp.where(hit, jnp.where(through, face, along), position[:, axis]))
        into_face = side * velocity[:, axis] < 0.0
        new_velocity.append(jnp.where(hit & through & into_face, 0.0, velocity[:, axis]))
    return jnp.stack(new_position, axis=1), jnp.stack(new_velocity, axis=1)
