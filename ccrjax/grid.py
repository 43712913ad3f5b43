"""A grid of independent runs (seeds x lambda values x configurations) spread over devices.

The experiments train many runs of one program at once: ``jax.vmap`` over a
leading *grid* axis (one entry per seed, lambda value, penalty ...). This module
shards that axis over every device JAX sees, so the same command uses one CPU,
all GPUs of a machine, or the devices of several machines:

* the grid is padded to a multiple of the device count (the padding repeats the
  last entry and is dropped from the results);
* inputs are placed with ``NamedSharding(mesh, P("grid"))`` on a one-axis mesh of
  all devices, and the vmapped program is jitted with the same sharding for its
  outputs; the runs are independent, so XLA partitions the program along the
  grid with no communication between devices;
* results come back to every host whole (``process_allgather`` when several
  processes take part).

Several machines: start the same command on each host after
``jax.distributed.initialize()`` (``ccrjax.grid.initialize_distributed`` reads the
usual ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID`` variables, or
the cluster's own, e.g. SLURM's); every process builds the same grid inputs
(they are deterministic functions of the command line), feeds its own devices'
slices, and receives every result.

On CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` makes two devices of
one machine's cores; ``tests/test_grid.py`` checks that sharded results equal
single-device results.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

GRID_AXIS = "grid"


def initialize_distributed() -> bool:
    """``jax.distributed.initialize()`` when the environment describes several processes.

    Returns whether it was called. Reads ``JAX_COORDINATOR_ADDRESS`` (and lets JAX find the
    process count and index, from ``JAX_NUM_PROCESSES``/``JAX_PROCESS_ID`` or a cluster
    manager such as SLURM). Call it before anything else touches JAX's devices.
    """
    if not os.environ.get("JAX_COORDINATOR_ADDRESS") and not os.environ.get("SLURM_JOB_ID"):
        return False
    jax.distributed.initialize()
    return True


def grid_mesh(devices: list | None = None) -> Mesh:
    """A one-axis mesh (``"grid"``) over ``devices`` (default: every device JAX sees)."""
    devices = jax.devices() if devices is None else devices
    return Mesh(np.asarray(devices), (GRID_AXIS,))


def padded_size(size: int, num_devices: int) -> int:
    return num_devices * math.ceil(size / num_devices)


def _pad(tree: Any, size: int, target: int) -> Any:
    if target == size:
        return tree
    return jax.tree_util.tree_map(
        lambda x: np.concatenate([x, np.repeat(x[-1:], target - size, axis=0)]), tree
    )


def _global(tree: Any, sharding: NamedSharding) -> Any:
    """Host arrays (the same on every process) as global arrays with ``sharding``."""

    def place(x: np.ndarray) -> jax.Array:
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree_util.tree_map(place, tree)


def _to_host(tree: Any) -> Any:
    if jax.process_count() == 1:
        return jax.device_get(tree)
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)


class GridProgram:
    """``function`` (one run) vmapped over a grid axis and sharded over ``mesh``'s devices.

    ``GridProgram(f)(grid_inputs)`` returns ``vmap(f)(grid_inputs)`` as host (numpy)
    arrays. ``grid_inputs`` is a pytree whose leaves share the leading grid axis.
    Compile ahead of time with :meth:`compile` to time the compilation on its own.
    """

    def __init__(self, function: Callable[[Any], Any], mesh: Mesh | None = None) -> None:
        self.mesh = grid_mesh() if mesh is None else mesh
        self.sharding = NamedSharding(self.mesh, P(GRID_AXIS))
        self.function = function
        self._jitted = jax.jit(jax.vmap(function), in_shardings=self.sharding,
                               out_shardings=self.sharding)
        self._compiled: dict[Any, Any] = {}

    @property
    def num_devices(self) -> int:
        return self.mesh.devices.size

    def _prepare(self, inputs: Any) -> tuple[Any, int]:
        leaves = jax.tree_util.tree_leaves(inputs)
        size = int(np.shape(leaves[0])[0])
        host = jax.tree_util.tree_map(np.asarray, inputs)
        padded = _pad(host, size, padded_size(size, self.num_devices))
        return _global(padded, self.sharding), size

    @staticmethod
    def _signature(placed: Any) -> Any:
        return jax.tree_util.tree_structure(placed), tuple(
            (x.shape, x.dtype) for x in jax.tree_util.tree_leaves(placed))

    def compile(self, inputs: Any, optimize: bool = True) -> None:
        """Compiles for inputs like ``inputs`` ahead of the call. ``optimize=False`` compiles
        at XLA's lowest backend optimisation level: about half the compile time on CPU and a
        slower program, for smoke tests whose programs run for moments."""
        placed, _ = self._prepare(inputs)
        key = self._signature(placed)
        if key not in self._compiled:
            lowered = self._jitted.lower(placed)
            options = None if optimize else {"xla_backend_optimization_level": 0}
            self._compiled[key] = lowered.compile(compiler_options=options)

    def __call__(self, inputs: Any) -> Any:
        placed, size = self._prepare(inputs)
        run = self._compiled.get(self._signature(placed), self._jitted)
        out = _to_host(run(placed))
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[:size], out)


def stack_keys(seeds: list[int]) -> jax.Array:
    """One ``PRNGKey(seed)`` per seed, stacked: ``uint32[len(seeds), 2]``."""
    return jnp.stack([jax.random.PRNGKey(seed) for seed in seeds])
