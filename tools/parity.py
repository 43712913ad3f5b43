"""Fingerprints of short fixed-seed training runs, to show a refactoring changed nothing.

    python tools/parity.py --out before.json     # on the old code
    python tools/parity.py --check before.json   # on the new code: exit 1 on any difference
    python tools/parity.py --check before.json --variants plain ccr   # only those variants

Trains every learner with every variant for a few iterations at a tiny size (2 seeds,
learning from the 40th transition, so updates happen) and records, per run, a SHA-256 of
every leaf of the final training state and of the evaluation history. Equal digests mean
bit-identical parameters, optimiser states, buffers, keys and metrics. ``--check`` compares
the runs both have; runs missing from the baseline (variants added since) are listed as new,
not as differences, and baseline runs not made here (``--variants``) as not checked.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys

import jax
import jax.numpy as jnp
import numpy as np

from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.agents.maac import MAACConfig
from ccrjax.training import ALGOS, VARIANTS, TrainConfig, make_train


def digest(tree) -> str:
    hasher = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(tree):
        array = np.asarray(leaf)
        hasher.update(str(array.dtype).encode() + str(array.shape).encode())
        hasher.update(np.ascontiguousarray(array).tobytes())
    return hasher.hexdigest()


def fingerprints(variants: tuple[str, ...] = VARIANTS) -> dict[str, dict[str, str]]:
    result = {}
    for algo in ALGOS:
        for variant in variants:
            config = TrainConfig(
                algo=algo, scenario="hidden_obstacle", variant=variant, num_envs=2,
                episode_length=10, total_env_steps=400, eval_every=200, eval_episodes=4,
                learning_starts=40,
                learner=MAACConfig(batch_size=32, policy_hidden=(8,), critic_hidden=8,
                                   attention_heads=2, update_every=20, gradient_steps=1)
                if algo == "maac" else
                DDPGConfig(batch_size=32, actor_hidden=(8,), critic_hidden=(8,),
                           update_every=20))
            program = make_train(config)
            keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1)])
            state, history = jax.jit(jax.vmap(program.train))(keys)
            result[f"{algo}-{variant}"] = {"state": digest(state), "history": digest(history)}
            print(f"{algo}-{variant}: {result[f'{algo}-{variant}']['state'][:16]}",
                  file=sys.stderr, flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--out")
    group.add_argument("--check")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
                        help="the variants to train (default: all)")
    args = parser.parse_args()
    found = fingerprints(tuple(args.variants))
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(found, handle, indent=1)
        return 0
    with open(args.check) as handle:
        expected = json.load(handle)
    compared = sorted(k for k in expected if k in found)
    different = [k for k in compared if expected[k] != found[k]]
    new = sorted(set(found) - set(expected))
    unchecked = sorted(set(expected) - set(found))
    print(f"identical ({len(compared)} runs)" if not different else f"different: {different}")
    if new:
        print(f"new (not in {args.check}, not compared): {new}")
    if unchecked:
        print(f"not checked (not run here): {unchecked}")
    return 1 if different or not compared else 0


if __name__ == "__main__":
    raise SystemExit(main())
