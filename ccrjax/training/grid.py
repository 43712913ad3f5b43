"""A grid of independent runs (seeds x lambda values x configurations) spread over devices.

The experiments train many runs of one program at once: ``jax.vmap`` over a
leading *grid* axis (one entry per seed, lambda value, penalty ...). This module
shards that axis over every device JAX sees, so the same command uses one CPU,
all GPUs of a machine, or the devices of several machines:

* the grid is padded to a multiple of the device count (the padding repeats the
  last entry and is dropped from the results);
* inputs are placed with ``NamedSharding(mesh, P("grid"))`` on a one-axis mesh of
  all devices, and each vmapped program is jitted with the same sharding for its
  outputs; the runs are independent, so XLA partitions the program along the
  grid with no communication between devices;
* results come back to every host whole (``process_allgather`` when several
  processes take part).

Several processes (machines): a command that joins them into one JAX job before anything
touches the devices (:mod:`ccrjax.run.distributed`) and then trains the same grid in every
process gets a mesh over all their devices; every process builds the same grid inputs
(deterministic functions of the configuration), feeds its own devices' slices, and receives
every result. ``tests/test_distributed.py`` checks that two processes give the same results,
bit for bit, as one process over the same number of devices.

On CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` makes two devices of
one machine's cores; ``tests/test_grid.py`` checks that sharded results equal
single-device results.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ccrjax.training.acting import run_episode
from ccrjax.training.config import TrainConfig, make_env
from ccrjax.training.program import make_train

GRID_AXIS = "grid"


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

    return multihost_utils.process_allgather(tree, tiled=True)


class GridProgram:
    """``function`` (one run) vmapped over a grid axis and sharded over ``mesh``'s devices.

    ``GridProgram(f)(grid_inputs)`` returns ``vmap(f)(grid_inputs)`` as host (numpy)
    arrays. ``grid_inputs`` is a pytree whose leaves share the leading grid axis.
    Compile ahead of time with :meth:`compile` to time the compilation on its own.

    :meth:`place` and :meth:`apply` keep inputs and outputs on the devices (padded to the
    device count), for a program called again on its own output: with ``donate=True`` the
    input's memory is reused for the output, so a state of many gigabytes is held once.
    """

    def __init__(self, function: Callable[[Any], Any], mesh: Mesh | None = None,
                 donate: bool = False) -> None:
        self.mesh = grid_mesh() if mesh is None else mesh
        self.sharding = NamedSharding(self.mesh, P(GRID_AXIS))
        self.function = function
        self._jitted = jax.jit(jax.vmap(function), in_shardings=self.sharding,
                               out_shardings=self.sharding,
                               donate_argnums=(0,) if donate else ())
        self._compiled: dict[Any, Any] = {}

    @property
    def num_devices(self) -> int:
        return self.mesh.devices.size

    def place(self, inputs: Any) -> tuple[Any, int]:
        """Host ``inputs`` padded to the device count and placed on the devices; and the
        grid's size before padding."""
        leaves = jax.tree_util.tree_leaves(inputs)
        size = int(np.shape(leaves[0])[0])
        host = jax.tree_util.tree_map(np.asarray, inputs)
        padded = _pad(host, size, padded_size(size, self.num_devices))
        return _global(padded, self.sharding), size

    def abstract(self, tree: Any) -> Any:
        """``tree``'s leaves (arrays or shape structs, leading axis already padded) as shape
        structs with this program's sharding: what :meth:`compile_for` and a restore take."""
        return jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=self.sharding), tree)

    @staticmethod
    def _signature(placed: Any) -> Any:
        return jax.tree_util.tree_structure(placed), tuple(
            (x.shape, x.dtype) for x in jax.tree_util.tree_leaves(placed))

    def compile_for(self, placed: Any, optimize: bool = True) -> None:
        """Compiles for placed inputs (or their :meth:`abstract` shapes) ahead of the call.
        ``optimize=False`` compiles at XLA's lowest backend optimisation level: about half
        the compile time on CPU and a slower program, for smoke tests whose programs run
        for moments."""
        key = self._signature(placed)
        if key not in self._compiled:
            lowered = self._jitted.lower(placed)
            options = None if optimize else {"xla_backend_optimization_level": 0}
            self._compiled[key] = lowered.compile(compiler_options=options)

    def compile(self, inputs: Any, optimize: bool = True) -> None:
        """:meth:`compile_for` host inputs like ``inputs``."""
        self.compile_for(self.place(inputs)[0], optimize)

    def apply(self, placed: Any) -> Any:
        """The program on placed inputs; the outputs stay on the devices, padded."""
        return self._compiled.get(self._signature(placed), self._jitted)(placed)

    def __call__(self, inputs: Any) -> Any:
        placed, size = self.place(inputs)
        return fetch(self.apply(placed), size)


def fetch(placed: Any, size: int) -> Any:
    """Placed outputs as host (numpy) arrays, the padding dropped."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[:size], _to_host(placed))


def stack_keys(seeds: list[int]) -> jax.Array:
    """One ``PRNGKey(seed)`` per seed, stacked: ``uint32[len(seeds), 2]``."""
    return jnp.stack([jax.random.PRNGKey(seed) for seed in seeds])


@dataclasses.dataclass
class GridRuns:
    """The results of :func:`train_grid`: entry ``g`` is ``seeds[g]`` with ``params[...][g]``."""

    config: TrainConfig
    seeds: list[int]
    params: dict[str, np.ndarray]  # [G] per transform parameter
    history: dict[str, np.ndarray]  # [G, evaluations + 1] per metric (and env_steps)
    policy: Any  # (learner state, transform state), leaves [G, ...]
    episodes: dict[str, np.ndarray] | None  # recorded evaluation episodes, leaves [G, ...]
    # [G] the first iteration whose updates went non-finite, -1 where none: that
    # iteration's updates were skipped (the learner kept its last finite state), as were
    # those of every later iteration that went non-finite.
    nonfinite_iteration: np.ndarray
    compile_s: float
    run_s: float

    @property
    def final(self) -> dict[str, np.ndarray]:
        """The last evaluation of every run, ``[G]`` per metric."""
        return {name: values[:, -1] for name, values in self.history.items()}

    def select(self, mask: np.ndarray) -> GridRuns:
        """The runs where ``mask`` ``[G]`` holds."""
        index = np.flatnonzero(mask)
        return dataclasses.replace(
            self,
            seeds=[self.seeds[i] for i in index],
            params={k: v[index] for k, v in self.params.items()},
            history={k: v[index] for k, v in self.history.items()},
            policy=jax.tree_util.tree_map(lambda x: x[index], self.policy),
            episodes=None if self.episodes is None
            else {k: v[index] for k, v in self.episodes.items()},
            nonfinite_iteration=self.nonfinite_iteration[index],
        )


@dataclasses.dataclass(frozen=True)
class GridProgress:
    """A grid part-way through training: every run's ``TrainState`` (on the devices, padded
    to the device count), the evaluation points so far (host arrays ``[runs]`` per metric,
    the untrained policies' first) and the seconds spent training them."""

    state: Any
    history: list[dict[str, np.ndarray]]
    run_s: float

    @property
    def evaluations(self) -> int:
        """Evaluations after the first: chunks of ``eval_every`` steps trained."""
        return len(self.history) - 1


class GridTraining:
    """A grid of runs of one configuration, trained together by sharded programs.

    Entry ``g`` trains with seed ``seeds[g]`` and the transform numbers ``params[name][g]``
    (e.g. ``{"lam": [...]}``, ``{"penalty": [...]}``); the others take the configuration's
    values. With ``record_episodes > 0`` the trained teams then run that many fresh
    evaluation episodes each (deterministic policies; the same starts and hazards for every
    entry, drawn from ``record_key``) and :attr:`GridRuns.episodes` holds what happened.

    Training is three compiled programs, each vmapped over the grid: ``start`` (every run's
    initial state and its untrained policy's evaluation), ``chunk`` (``eval_every`` steps
    then an evaluation: :meth:`ccrjax.training.program.TrainProgram.chunk`, called once per
    evaluation on the state it returned, which stays on the devices and is donated, so it is
    held once) and ``finish`` (the policies and the recorded episodes). A caller can look at
    (and save) the state between chunks and start again from it (:meth:`run`'s ``resume``
    and ``after_chunk``; :mod:`ccrjax.run.grid_checkpoint` saves and restores it). :meth:`compile`
    and :meth:`run` are separate so that a caller can compile the next grid while this one
    trains.
    """

    def __init__(
        self,
        config: TrainConfig,
        seeds: Sequence[int],
        params: dict[str, Sequence[float]] | None = None,
        *,
        record_episodes: int = 0,
        record_key: jax.Array | None = None,
        mesh: Mesh | None = None,
    ) -> None:
        self.config = config
        self.seeds = [int(s) for s in seeds]
        program = make_train(config)
        self.program = program
        defaults = program.default_transform_params()
        given = {k: np.asarray(v, np.float32) for k, v in (params or {}).items()}
        for name, values in given.items():
            if name not in defaults:
                raise ValueError(f"variant {config.variant!r} takes the run parameters "
                                 f"{sorted(defaults)}, not {name!r}")
            if values.shape != (len(self.seeds),):
                raise ValueError(f"params[{name!r}] must hold one value per seed "
                                 f"({len(self.seeds)})")
        self.params = {name: given.get(name, np.full(len(self.seeds), value, np.float32))
                       for name, value in defaults.items()}
        self.inputs = {"key": np.asarray(stack_keys(self.seeds)), "params": self.params}
        self.record_episodes = record_episodes
        record_env = make_env(config, record_episodes) if record_episodes else None
        record_key = jax.random.PRNGKey(0) if record_key is None else record_key
        self.record_key = np.asarray(record_key)

        def start(entry: dict[str, Any]):
            state = program.init(entry["key"], entry["params"])
            return state, program.evaluation_point(state)

        def chunk(state):
            state, point, _ = program.chunk(state)
            return state, point

        def finish(state):
            out = {"policy": (state.learner, state.transform),
                   "nonfinite": state.nonfinite_iteration}
            if record_env is not None:
                def greedy(obs, step_key):
                    return program.learner.act(state.learner, obs, step_key, False)

                _, episode = run_episode(record_env, program.transform, state.transform,
                                         greedy, program.learner.discrete, record_key)
                out["episodes"] = {
                    "position": episode.position,
                    "danger": episode.danger,
                    "success": episode.success[-1],  # [N, E]: in the target area at the end
                    "hazard_centre": episode.hazard.centre,
                    "hazard_half_extent": episode.hazard.half_extent,
                    **episode.info,
                }
            return out

        mesh = grid_mesh() if mesh is None else mesh
        self._start = GridProgram(start, mesh)
        self._chunk = GridProgram(chunk, mesh, donate=True)
        self._finish = GridProgram(finish, mesh)
        self.compile_s = 0.0

    @property
    def num_devices(self) -> int:
        return self._start.num_devices

    @property
    def num_runs(self) -> int:
        return len(self.seeds)

    def abstract_state(self) -> Any:
        """The shapes (padded) and sharding of every run's ``TrainState``, as ``chunk``
        takes and returns it."""
        placed, _ = self._start.place(self.inputs)
        state, _ = jax.eval_shape(jax.vmap(self._start.function), placed)
        return self._chunk.abstract(state)

    def compile(self, optimize: bool = True) -> float:
        """Compiles the three programs (thread-safe to call from a worker); returns the
        seconds. ``optimize=False``: see :meth:`ccrjax.training.grid.GridProgram.compile_for`."""
        began = time.perf_counter()
        self._start.compile(self.inputs, optimize)
        state = self.abstract_state()
        self._chunk.compile_for(state, optimize)
        self._finish.compile_for(state, optimize)
        self.compile_s = time.perf_counter() - began
        return self.compile_s

    def run(self, resume: GridProgress | None = None,
            after_chunk: Callable[[GridProgress], None] | None = None) -> GridRuns:
        """Trains every entry (from ``resume`` if given) and returns the results.

        ``after_chunk(progress)`` is called after every chunk but the last; the state it
        sees is donated to the next chunk when it returns, so it must not keep it. An entry
        whose update went non-finite trains on from its last finite state (the program
        skips such updates) and :attr:`GridRuns.nonfinite_iteration` says where.
        """
        began = time.perf_counter()
        size = self.num_runs
        if resume is None:
            placed, _ = self._start.place(self.inputs)
            state, point = self._start.apply(placed)
            history, earlier_s = [fetch(point, size)], 0.0
        else:
            state, history, earlier_s = resume.state, list(resume.history), resume.run_s
        total = self.program.num_evaluations
        for done in range(len(history), total + 1):
            state, point = self._chunk.apply(state)
            history.append(fetch(point, size))
            if after_chunk is not None and done < total:
                after_chunk(GridProgress(state, history,
                                         earlier_s + time.perf_counter() - began))
        out = fetch(self._finish.apply(state), size)
        return GridRuns(config=self.config, seeds=self.seeds, params=self.params,
                        history={k: np.stack([point[k] for point in history], axis=1)
                                 for k in history[0]},
                        policy=out["policy"], episodes=out.get("episodes"),
                        nonfinite_iteration=np.asarray(out["nonfinite"], np.int64),
                        compile_s=self.compile_s,
                        run_s=earlier_s + time.perf_counter() - began)


def train_grid(
    config: TrainConfig,
    seeds: Sequence[int],
    params: dict[str, Sequence[float]] | None = None,
    *,
    record_episodes: int = 0,
    record_key: jax.Array | None = None,
    log=None,
) -> GridRuns:
    """Compiles and runs a :class:`GridTraining` (see there)."""
    training = GridTraining(config, seeds, params, record_episodes=record_episodes,
                            record_key=record_key)
    compile_s = training.compile()
    if log:
        log(f"  compiled in {compile_s:.1f} s ({training.num_devices} device(s)); "
            f"training {len(training.seeds)} run(s) ...")
    return training.run()
