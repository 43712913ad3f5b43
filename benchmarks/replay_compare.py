"""Our replay buffer against flashbax's item buffer, used the way training uses a buffer.

    python benchmarks/replay_compare.py                  # table
    python benchmarks/replay_compare.py --json           # one JSON object per line
    python benchmarks/replay_compare.py --capacity 200000

Both buffers hold the transitions of one training configuration (default: MADDPG on
``hidden_obstacle``, 5 robots; the shapes are read from ``make_train(config).init``'s
buffer), one buffer per seed, every operation ``jax.vmap``-ped over ``--seeds`` seeds
and jitted, as ``jax.vmap(program.train)`` does:

* ours: :mod:`ccrjax.agents.replay`, whole episodes (each observation stored once),
  one block of ``num_envs`` episodes of ``episode_length`` steps per insert, running
  reward sums for MAAC;
* flashbax: ``fbx.make_item_buffer(max_length=capacity, sample_batch_size=batch,
  add_batches=True)``, the whole ``Transition`` (``obs`` and ``next_obs``) stored per
  item; an insert is the same rollout block flattened to ``num_envs * episode_length``
  items. Its sampling, like ours, is uniform with replacement over the items held (an
  index drawn by ``jax.random.randint`` over ``[0, items held)``).

It measures, for each buffer:

1. ``bytes_per_seed``: bytes of all leaves of one seed's state, at ``--capacity`` and at
   the capacity a default run of the configuration uses (``TrainConfig.replay_capacity``);
2. ``insert_us``: one iteration's insert (``num_envs x episode_length`` transitions, every
   seed), state donated; ``scan``: ``--calls`` inserts inside one compiled ``lax.scan`` (as
   in training, where the insert is part of the compiled iteration), ``call``: ``--calls``
   separate jitted calls (as a Python-driven loop would);
3. ``sample_us``: one batch of ``batch_size`` transitions per seed, the same two ways;
4. ``checkpoint_bytes``: bytes on disk of the state of every seed saved with orbax's
   ``StandardCheckpointer`` (what :mod:`ccrjax.run.checkpoint` saves through) once the
   buffers are half full, with save and restore times, and whether the restored state is
   identical and samples identically (exact resume);
5. sanity: after the same inserts both buffers hold the same number of transitions (with
   and without wrap-around), at a small capacity exactly the same transitions, and every
   sampled transition is one that was inserted and is still held, field for field.

Times are medians over ``--repeats`` rounds after compilation, the buffers timed in turns
within each round; the ``flashbax/ours`` row gives flashbax's number over ours from the same
run (for times, the median over rounds of each round's ratio). The
data are random (uniform observations and actions, normal rewards) with the transition's
id written into robot 0's reward so samples can be traced back; observations follow the
episode (``next_obs[t] == obs[t + 1]``), as the rollout's do.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import platform
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from ccrjax import cli
from ccrjax.agents import replay
from ccrjax.agents.types import Transition
from ccrjax.envs.scenarios import SCENARIOS
from ccrjax.training import ALGOS, TrainConfig, make_train


@dataclasses.dataclass(frozen=True)
class Contender:
    """One buffer's pure functions, for one seed (the caller vmaps them)."""

    name: str
    init: Callable[[], Any]  # an empty state
    insert: Callable[[Any, Transition], Any]  # a rollout block, leaves [T, E, ...]
    sample: Callable[[Any, jax.Array], Transition]  # a batch, leaves [batch, ...]
    size: Callable[[Any], jax.Array]  # transitions held, int[]


@dataclasses.dataclass(frozen=True)
class Layout:
    """What the configuration fixes: one transition's shapes and the sizes of a block."""

    example: Transition  # jax.ShapeDtypeStruct leaves, one transition, no batch axis
    steps: int  # episode_length
    envs: int  # num_envs
    batch: int  # learner batch size
    default_capacity: int  # TrainConfig.replay_capacity

    @property
    def block(self) -> int:
        return self.steps * self.envs


def read_layout(config: TrainConfig) -> Layout:
    """The transition's leaf shapes as ``make_train(config).init`` lays out its buffer."""
    state = jax.eval_shape(make_train(config).init, jax.random.PRNGKey(0))
    b = state.buffer  # obs [C, T + 1, N, F], action [C, T, ...], reward [C, T, N], done [C, T]

    def one(x: jax.ShapeDtypeStruct) -> jax.ShapeDtypeStruct:
        return jax.ShapeDtypeStruct(x.shape[2:], x.dtype)

    example = Transition(
        obs=one(b.obs), action=one(b.action), reward=one(b.reward), next_obs=one(b.obs),
        done=one(b.done),
    )
    return Layout(
        example=example,
        steps=config.episode_length,
        envs=config.num_envs,
        batch=config.resolved_learner.batch_size,
        default_capacity=config.replay_capacity,
    )


def ours(layout: Layout, capacity: int) -> Contender:
    return Contender(
        name="ours",
        init=lambda: replay.init_replay(layout.example, capacity // layout.steps, layout.steps),
        insert=replay.add_episodes,
        sample=lambda state, key: replay.sample(state, key, layout.batch),
        size=lambda state: state.size,
    )


def flashbax_items(layout: Layout, capacity: int) -> Contender:
    buffer = fbx.make_item_buffer(
        max_length=capacity, min_length=1, sample_batch_size=layout.batch, add_batches=True
    )

    def init() -> Any:
        return buffer.init(jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), layout.example))

    def insert(state: Any, block: Transition) -> Any:
        items = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), block)  # [T * E, ...]
        return buffer.add(state, items)

    def sample(state: Any, key: jax.Array) -> Transition:
        return buffer.sample(state, key).experience

    def size(state: Any) -> jax.Array:
        return jnp.where(state.is_full, capacity, state.current_index)

    return Contender("flashbax", init, insert, sample, size)


# ---------------------------------------------------------------------------- data
def make_block(layout: Layout, key: jax.Array, index: jax.Array) -> Transition:
    """Rollout block number ``index``: leaves ``[T, E, ...]``, step-major as the rollout makes
    them; transition ``(t, e)`` has id ``index * T * E + e * T + t`` in ``reward[..., 0]``."""
    t, e = layout.steps, layout.envs
    k_obs, k_act, k_rew = jax.random.split(key, 3)
    ex = layout.example
    path = jax.random.uniform(k_obs, (t + 1, e) + ex.obs.shape, ex.obs.dtype)
    if jnp.issubdtype(ex.action.dtype, jnp.integer):
        action = jax.random.randint(k_act, (t, e) + ex.action.shape, 0, 5, ex.action.dtype)
    else:
        action = jax.random.uniform(k_act, (t, e) + ex.action.shape, ex.action.dtype, -1.0, 1.0)
    ids = index * (t * e) + jnp.arange(e)[None, :] * t + jnp.arange(t)[:, None]
    reward = jax.random.normal(k_rew, (t, e) + ex.reward.shape, ex.reward.dtype)
    reward = reward.at[..., 0].set(ids.astype(ex.reward.dtype))
    return Transition(
        obs=path[:-1], action=action, reward=reward, next_obs=path[1:],
        done=jnp.zeros((t, e) + ex.done.shape, ex.done.dtype),
    )


def seed_blocks(layout: Layout, seeds: int, index: jax.Array) -> Transition:
    """Block ``index`` of every seed (leaves ``[S, T, E, ...]``), each seed its own data."""
    keys = jax.vmap(lambda s: jax.random.fold_in(jax.random.PRNGKey(s), index))(
        jnp.arange(seeds)
    )
    return jax.vmap(lambda k: make_block(layout, k, index))(keys)


def transition_id(batch: Transition) -> np.ndarray:
    return np.asarray(batch.reward[..., 0]).astype(np.int64)


def empty_states(contender: Contender, seeds: int) -> Any:
    return jax.jit(jax.vmap(lambda _: contender.init()))(jnp.arange(seeds))


def filler(contender: Contender, layout: Layout, seeds: int) -> Callable[[Any, int, int], Any]:
    """``fill(states, first, count)``: inserts blocks ``first .. first + count - 1``."""

    def fill(states: Any, first: jax.Array, count: int) -> Any:
        def body(i: jax.Array, states: Any) -> Any:
            return jax.vmap(contender.insert)(states, seed_blocks(layout, seeds, first + i))

        return jax.lax.fori_loop(0, count, body, states)

    return jax.jit(fill, static_argnums=2, donate_argnums=0)


def state_bytes(tree: Any) -> int:
    return sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize
               for x in jax.tree_util.tree_leaves(tree))


def per_seed_bytes(contender: Contender) -> int:
    return state_bytes(jax.eval_shape(contender.init))


# ---------------------------------------------------------------------------- sanity
def held_ids(total_blocks: int, capacity_blocks: int, block: int) -> np.ndarray:
    """Ids of the transitions a ring of ``capacity_blocks`` blocks holds after ``total_blocks``
    inserts: the most recent ones."""
    first = max(0, total_blocks - capacity_blocks)
    return np.arange(first * block, total_blocks * block)


def check_sample(layout: Layout, batch: Transition, held: np.ndarray) -> dict[str, bool]:
    """Each seed's sampled transitions are held ones, field for field (recomputed)."""
    batch = jax.tree.map(np.asarray, batch)
    ids = transition_id(batch)  # [S, B]
    held_ok = bool(np.isin(ids, held).all())
    exact = True
    block = layout.block
    for s in range(ids.shape[0]):
        blocks = np.unique(ids[s] // block)
        key = jax.random.PRNGKey(s)
        data = jax.tree.map(np.asarray, jax.vmap(
            lambda i, key=key: make_block(layout, jax.random.fold_in(key, i), i)
        )(jnp.asarray(blocks)))  # leaves [blocks, T, E, ...]
        j = np.searchsorted(blocks, ids[s] // block)
        e, t = np.divmod(ids[s] % block, layout.steps)
        for name in ("obs", "action", "reward", "next_obs", "done"):
            want = getattr(data, name)[j, t, e]
            exact &= bool(np.array_equal(want, getattr(batch, name)[s]))
    return {"samples_are_held_transitions": held_ok, "samples_match_inserted_data": exact}


def sanity_small(layout: Layout, seeds: int, capacity_blocks: int = 10) -> dict[str, Any]:
    """At a small capacity, before and after wrap-around: equal sizes, the same transitions
    held, samples exactly the inserted transitions."""
    capacity = capacity_blocks * layout.block
    contenders = [ours(layout, capacity), flashbax_items(layout, capacity)]
    out: dict[str, Any] = {"sanity_capacity": capacity}
    for total in (3, capacity_blocks + 3):
        sizes, stored = {}, {}
        for c in contenders:
            states = filler(c, layout, seeds)(empty_states(c, seeds), jnp.int32(0), total)
            sizes[c.name] = np.asarray(jax.vmap(c.size)(states)).tolist()
            keys = jax.random.split(jax.random.PRNGKey(7), seeds)
            batch = jax.vmap(c.sample)(states, keys)
            held = held_ids(total, capacity_blocks, layout.block)
            checks = check_sample(layout, batch, held)
            for k, v in checks.items():
                out[f"{c.name}_{k}_after_{total}"] = v
            reward = np.asarray(states.reward if c.name == "ours" else states.experience.reward)
            ids = reward[..., 0].reshape(seeds, -1).astype(np.int64)  # [S, capacity]
            # Both fill their storage from index 0: the first `size` items are the ones held.
            stored[c.name] = [np.sort(ids[s][: sizes[c.name][s]]) for s in range(seeds)]
            out[f"{c.name}_holds_exactly_expected_after_{total}"] = all(
                np.array_equal(x, held) for x in stored[c.name]
            )
        out[f"sizes_after_{total}_inserts"] = sizes
        out[f"same_size_after_{total}"] = sizes["ours"] == sizes["flashbax"]
    return out


# ---------------------------------------------------------------------------- timing
def timers(contender: Contender) -> dict[str, Callable[..., Any]]:
    def scan_insert(states: Any, blocks: Transition) -> Any:  # blocks [K, S, T, E, ...]
        def step(states: Any, block: Transition) -> tuple[Any, None]:
            return jax.vmap(contender.insert)(states, block), None

        return jax.lax.scan(step, states, blocks)[0]

    def scan_sample(states: Any, keys: jax.Array) -> Transition:  # keys [K, S]
        # Each batch is materialised (as a learner update's input is) and carried, so none
        # is optimised away; the last one is returned.
        def step(batch: Transition, keys: jax.Array) -> tuple[Transition, None]:
            return jax.vmap(contender.sample)(states, keys), None

        shapes = jax.eval_shape(jax.vmap(contender.sample), states, keys[0])
        first = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
        return jax.lax.scan(step, first, keys)[0]

    return {
        "scan_insert": jax.jit(scan_insert, donate_argnums=0),
        "call_insert": jax.jit(jax.vmap(contender.insert), donate_argnums=0),
        "scan_sample": jax.jit(scan_sample),
        "call_sample": jax.jit(jax.vmap(contender.sample)),
    }


def timed(fn: Callable[[], Any]) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def run_round(
    fns: dict[str, Callable[..., Any]], states: Any, blocks: Transition, keys: jax.Array,
    calls: int,
) -> tuple[Any, dict[str, float]]:
    """One round of the four measurements; returns the state and seconds per operation.

    ``blocks``/``keys``: leaves ``[calls, S, ...]``, the inputs of the ``calls`` operations;
    the separate calls get them sliced beforehand, so only the calls are timed."""
    times = {}
    box = [states]
    block_list = [jax.tree.map(lambda x, k=k: x[k], blocks) for k in range(calls)]
    key_list = [keys[k] for k in range(calls)]
    jax.block_until_ready((block_list, key_list))

    def scan_insert() -> Any:
        box[0] = fns["scan_insert"](box[0], blocks)
        return box[0]

    def call_insert() -> Any:
        for block in block_list:
            box[0] = fns["call_insert"](box[0], block)
        return box[0]

    times["insert_scan"] = timed(scan_insert) / calls
    times["insert_call"] = timed(call_insert) / calls
    times["sample_scan"] = timed(lambda: fns["scan_sample"](box[0], keys)) / calls

    def call_sample() -> list[Transition]:
        return [fns["call_sample"](box[0], key) for key in key_list]

    times["sample_call"] = timed(call_sample) / calls
    return box[0], times


# ---------------------------------------------------------------------------- checkpoint
def checkpoint(states: Any, directory: Path, sample: Callable[..., Any]) -> dict[str, Any]:
    """Saves ``states`` with orbax, measures it on disk, restores it, checks exact resume."""
    path = directory / "state"
    checkpointer = ocp.StandardCheckpointer()
    start = time.perf_counter()
    checkpointer.save(path, states)
    checkpointer.wait_until_finished()
    save_s = time.perf_counter() - start
    on_disk = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), states)
    start = time.perf_counter()
    restored = checkpointer.restore(path, abstract)
    jax.block_until_ready(restored)
    restore_s = time.perf_counter() - start
    checkpointer.close()
    identical = all(
        bool(jnp.array_equal(a, b))
        for a, b in zip(jax.tree.leaves(states), jax.tree.leaves(restored), strict=True)
    )
    keys = jax.random.split(jax.random.PRNGKey(11), jax.tree.leaves(states)[0].shape[0])
    same_sample = all(
        bool(jnp.array_equal(a, b))
        for a, b in zip(jax.tree.leaves(sample(states, keys)),
                        jax.tree.leaves(sample(restored, keys)), strict=True)
    )
    del restored
    shutil.rmtree(path)
    return {
        "checkpoint_bytes": on_disk,
        "checkpoint_save_s": save_s,
        "checkpoint_restore_s": restore_s,
        "restored_identical": identical,
        "restored_samples_identical": same_sample,
    }


# ---------------------------------------------------------------------------- main
def measure(args: argparse.Namespace) -> list[dict[str, Any]]:
    config = TrainConfig(algo=args.algo, scenario=args.scenario)
    layout = read_layout(config)
    capacity = replay.replay_capacity(args.capacity, layout.block)
    seeds, calls = args.seeds, args.calls
    contenders = [ours(layout, capacity), flashbax_items(layout, capacity)]
    shapes = {k: [list(v.shape), str(v.dtype)] for k, v in vars(layout.example).items()
              if v is not None}  # a channel the configuration does not use (cost) is None
    base = {
        "algo": args.algo, "scenario": args.scenario, "seeds": seeds, "capacity": capacity,
        "block": layout.block, "batch": layout.batch, "transition": shapes,
        "device": jax.devices()[0].device_kind, "jax": jax.__version__,
        "flashbax": importlib.metadata.version("flashbax"),
    }
    rows: dict[str, dict[str, Any]] = {c.name: {**base, "buffer": c.name} for c in contenders}

    for c in contenders:
        rows[c.name]["bytes_per_seed"] = per_seed_bytes(c)
        default = ours if c.name == "ours" else flashbax_items
        rows[c.name]["bytes_per_seed_default_capacity"] = per_seed_bytes(
            default(layout, layout.default_capacity)
        )
        rows[c.name]["default_capacity"] = layout.default_capacity

    sanity = sanity_small(layout, seeds)

    # Fill every buffer half way, identically.
    half = capacity // layout.block // 2
    states: dict[str, Any] = {}
    for c in contenders:
        start = time.perf_counter()
        states[c.name] = filler(c, layout, seeds)(empty_states(c, seeds), jnp.int32(0), half)
        jax.block_until_ready(states[c.name])
        rows[c.name]["fill_half_s"] = time.perf_counter() - start
    held = held_ids(half, 2 * half, layout.block)
    keys = jax.random.split(jax.random.PRNGKey(3), seeds)
    for c in contenders:
        size = np.asarray(jax.vmap(c.size)(states[c.name])).tolist()
        rows[c.name]["size_after_fill"] = size
        ids = transition_id(jax.vmap(c.sample)(states[c.name], keys))
        rows[c.name]["big_samples_are_held_transitions"] = bool(np.isin(ids, held).all())
    sizes = [rows[c.name]["size_after_fill"] for c in contenders]
    sanity["same_size_after_half_fill"] = all(s == sizes[0] for s in sizes)

    with tempfile.TemporaryDirectory(dir=args.tmpdir) as tmp:
        for c in contenders:
            sample = jax.jit(jax.vmap(c.sample))
            rows[c.name].update(checkpoint(states[c.name], Path(tmp) / c.name, sample))

    # Timing: compile, then rounds with the buffers in turns.
    blocks = jax.vmap(lambda i: seed_blocks(layout, seeds, half + i))(jnp.arange(calls))
    sample_keys = jax.random.split(jax.random.PRNGKey(5), (calls, seeds))
    fns = {c.name: timers(c) for c in contenders}
    for c in contenders:
        start = time.perf_counter()
        states[c.name], _ = run_round(fns[c.name], states[c.name], blocks, sample_keys, calls)
        rows[c.name]["first_round_s"] = time.perf_counter() - start
    times: dict[str, dict[str, list[float]]] = {c.name: {} for c in contenders}
    for _ in range(args.repeats):
        for c in contenders:
            states[c.name], t = run_round(fns[c.name], states[c.name], blocks, sample_keys, calls)
            for k, v in t.items():
                times[c.name].setdefault(k, []).append(v)
    for c in contenders:
        for k, v in times[c.name].items():
            rows[c.name][f"{k}_us"] = statistics.median(v) * 1e6
            rows[c.name][f"{k}_us_all"] = [x * 1e6 for x in v]
        rows[c.name]["repeats"] = args.repeats
        rows[c.name]["calls_per_repeat"] = calls

    ratio_keys = [
        "bytes_per_seed", "bytes_per_seed_default_capacity", "insert_scan_us", "insert_call_us",
        "sample_scan_us", "sample_call_us", "checkpoint_bytes", "checkpoint_save_s",
        "checkpoint_restore_s",
    ]
    ratio = {**base, "buffer": "flashbax/ours"}
    for k in ratio_keys:
        if k.endswith("_us"):  # times: the median of each round's ratio (paired)
            pairs = zip(rows["flashbax"][k + "_all"], rows["ours"][k + "_all"], strict=True)
            ratio[k] = statistics.median(f / o for f, o in pairs)
        else:
            ratio[k] = rows["flashbax"][k] / rows["ours"][k]
    return [rows["ours"], rows["flashbax"], ratio, {**base, "buffer": "sanity", **sanity}]


def main(argv: list[str] | None = None) -> int:
    parser = cli.Parser(prog="python benchmarks/replay_compare.py",
                        description=__doc__.split("\n")[0])
    parser.add_argument("--algo", choices=ALGOS, default="maddpg",
                        help="learner whose transitions are stored (default: %(default)s)")
    parser.add_argument("--scenario", choices=tuple(SCENARIOS), default="hidden_obstacle",
                        help="scenario whose observations are stored (default: %(default)s)")
    parser.add_argument("--capacity", type=cli.positive_int, default=1_000_000,
                        help="transitions each buffer holds (default: %(default)s)")
    parser.add_argument("--seeds", type=cli.positive_int, default=3,
                        help="buffers side by side, one per seed (default: %(default)s)")
    parser.add_argument("--repeats", type=cli.positive_int, default=5,
                        help="timed repeats; the median is reported (default: %(default)s)")
    parser.add_argument("--calls", type=cli.positive_int, default=20,
                        help="operations per timed repeat (default: %(default)s)")
    parser.add_argument("--tmpdir", default=None,
                        help="where the checkpoints are written (default: a temporary folder)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per line instead of a table")
    args = parser.parse_args(argv)

    rows = measure(args)
    if args.json:
        for row in rows:
            print(json.dumps(row), flush=True)
    else:
        print_table(rows)
    return 0


def print_table(rows: list[dict[str, Any]]) -> None:
    """The rows of :func:`measure` (or of ``--json``'s output, read back) as a table."""
    mib = 2.0**20
    first = rows[0]
    print(f"{platform.node()} · {first['device']} · jax {first['jax']} · "
          f"flashbax {first['flashbax']} · {first['seeds']} seeds · capacity {first['capacity']:,}"
          f" (default run: {first['default_capacity']:,}) · transition {first['transition']}")
    header = (
        f"{'buffer':14} {'MiB/seed':>9} {'@default':>9} {'insert scan':>12} {'insert call':>12} "
        f"{'sample scan':>12} {'sample call':>12} {'ckpt MiB':>9} {'save s':>7} {'restore s':>9}"
    )
    print(header)
    print("-" * len(header))
    for row in rows[:3]:
        is_ratio = row["buffer"] == "flashbax/ours"
        scale = 1.0 if is_ratio else mib
        unit = "" if is_ratio else " us"
        print(
            f"{row['buffer']:14} {row['bytes_per_seed'] / scale:9.2f} "
            f"{row['bytes_per_seed_default_capacity'] / scale:9.2f} "
            + " ".join(f"{row[k]:{12 - len(unit)}.2f}{unit}" for k in (
                "insert_scan_us", "insert_call_us", "sample_scan_us", "sample_call_us"))
            + f" {row['checkpoint_bytes'] / scale:9.2f} {row['checkpoint_save_s']:7.2f}"
            f" {row['checkpoint_restore_s']:9.2f}"
        )
    print(f"times: median of {first['repeats']} rounds of {first['calls_per_repeat']} operations "
          "after compilation, per operation on every seed (vmapped); insert = one iteration's "
          f"{first['block']} transitions, sample = {first['batch']} per seed; checkpoint = every "
          "seed's state, half full; time ratios: median over rounds of the round's ratio")
    for row in rows[:2]:
        print(f"{row['buffer']}: sizes after half fill {row['size_after_fill']}, samples held: "
              f"{row['big_samples_are_held_transitions']}, restored identical: "
              f"{row['restored_identical']}, restored samples identical: "
              f"{row['restored_samples_identical']}")
    sanity = {k: v for k, v in rows[3].items() if k not in first}
    print("sanity:", json.dumps(sanity))


if __name__ == "__main__":
    raise SystemExit(main())
