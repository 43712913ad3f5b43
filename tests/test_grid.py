"""The grid of runs spread over devices: sharded results equal single-device results.

Runs in a subprocess with ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (two CPU
devices; the flag must be set before JAX starts), training a grid of 3 tiny runs (padded to
4) once on both devices and once on one, and comparing every parameter and metric. They
agree to float32 rounding (about 1e-6 relative): the partitioned program may add in
another order.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import json
    import jax
    import numpy as np
    from ccrjax.training.grid import grid_mesh
    from ccrjax.agents.ddpg import DDPGConfig
    from ccrjax.training.grid import GridTraining
    from ccrjax.training import TrainConfig

    assert jax.device_count() == 2, jax.devices()
    config = TrainConfig(
        algo="maddpg", scenario="hidden_obstacle", variant="ccr", num_envs=2, episode_length=10,
        total_env_steps=160, eval_every=80, eval_episodes=3, learning_starts=40,
        learner=DDPGConfig(batch_size=16, actor_hidden=(8,), critic_hidden=(8,), update_every=10),
    )
    results = {}
    for name, devices in (("two", jax.devices()), ("one", jax.devices()[:1])):
        training = GridTraining(config, [0, 1, 2], {"lam": [0.0, 30.0, 30.0]},
                                mesh=grid_mesh(devices))
        runs = training.run()
        leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(runs.policy)]
        results[name] = (runs.history, leaves, training.num_devices)
    (h2, p2, n2), (h1, p1, n1) = results["two"], results["one"]
    assert (n2, n1) == (2, 1)
    # Equal up to float32 rounding: the partitioned program may sum in another order.
    for key in h1:
        assert h1[key].shape == h2[key].shape == (3, 3), (key, h1[key].shape)
        np.testing.assert_allclose(h1[key], h2[key], rtol=1e-4, atol=1e-5)
    for a, b in zip(p1, p2, strict=True):
        assert a.shape == b.shape and a.shape[0] == 3
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    worst = max(float(np.max(np.abs(h1[k] - h2[k]))) for k in h1)
    distinct = not np.allclose(h1["return"][0], h1["return"][1])
    print(json.dumps({"worst": worst, "distinct": distinct}))
    """
)


@pytest.mark.slow
def test_sharded_grid_equals_single_device(subprocess_env):
    env = dict(subprocess_env)
    env["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    env["JAX_PLATFORMS"] = "cpu"  # on a GPU machine the default backend has one device
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["distinct"], "the runs of the grid should differ from each other"
    assert result["worst"] <= 1e-5, result  # the evaluation histories
