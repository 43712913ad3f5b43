"""A grid of runs trained in chunks, checkpointed, killed and resumed.

The experiments' programs run for hours (:mod:`ccrjax.run.grid_checkpoint`): a grid stopped
after a checkpoint and started again from it must give exactly the result of a grid that
ran through, and equal the pure program's ``train`` (the whole schedule in one scan); a
checkpoint of another grid is never resumed.
"""

from __future__ import annotations

import logging

import jax
import numpy as np
import pytest
from absl import logging as absl_logging

from ccrjax.agents.ddpg import DDPGConfig
from ccrjax.run.grid_checkpoint import train_resumably
from ccrjax.training import TrainConfig, make_train
from ccrjax.training.grid import GridTraining, stack_keys

CONFIG = TrainConfig(
    algo="iddpg", scenario="strong_wind", variant="ccr", num_envs=2, episode_length=10,
    total_env_steps=160, eval_every=40, eval_episodes=3, learning_starts=40,
    learner=DDPGConfig(batch_size=16, actor_hidden=(8,), critic_hidden=(8,), update_every=10),
)
SEEDS, LAMS = [3, 4], [0.0, 30.0]


class Killed(Exception):
    """Stands for the process being killed right after a checkpoint was written."""


def grid(**kwargs) -> GridTraining:
    return GridTraining(CONFIG, SEEDS, {"lam": LAMS}, **kwargs)


def leaves(tree) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


@pytest.fixture(scope="module")
def through():
    """The grid trained without interruption (and without checkpoints)."""
    return grid().run()


def test_the_chunked_grid_trains_what_the_pure_program_trains(through):
    program = make_train(CONFIG)
    params = {"lam": np.asarray(LAMS, np.float32)}
    state, history = jax.jit(jax.vmap(program.train))(stack_keys(SEEDS), params)
    assert through.history["return"].shape == (2, 5)
    for key, values in history.items():
        np.testing.assert_allclose(through.history[key], values, rtol=1e-5, atol=1e-6,
                                   err_msg=key)
    for ours, theirs in zip(leaves(through.policy), leaves((state.learner, state.transform)),
                            strict=True):
        np.testing.assert_allclose(ours, theirs, rtol=1e-4, atol=1e-5)
    assert not np.allclose(through.history["return"][0], through.history["return"][1])


def test_a_grid_killed_after_a_checkpoint_resumes_to_exactly_the_same_result(
        through, tmp_path):
    folder, lines = tmp_path / "partial", []

    def log_then_kill(line: str) -> None:
        lines.append(line)
        if "checkpoint after 2 of 4" in line:
            raise Killed

    with pytest.raises(Killed):
        train_resumably(grid(), folder, every_s=1e-9, log=log_then_kill)
    assert [int(p.name) for p in folder.iterdir() if p.name.isdigit()] == [80]

    resumed = train_resumably(grid(), folder, every_s=1e-9, log=lines.append,
                              note_first_s=0.0, note_every_s=0.0)
    assert any("resuming from its checkpoint after 2 of 4 evaluations" in line
               for line in lines), lines
    # Progress after every chunk but the last, counted from the resumed evaluations.
    notes = [line for line in lines if "evaluations trained" in line]
    assert len(notes) == 1 and "3 of 4 evaluations trained" in notes[0], lines
    assert "min left in this program" in notes[0]
    for key in through.history:
        np.testing.assert_array_equal(resumed.history[key], through.history[key], key)
    for ours, theirs in zip(leaves(resumed.policy), leaves(through.policy), strict=True):
        np.testing.assert_array_equal(ours, theirs)


def test_a_checkpoint_of_another_grid_is_set_aside_and_the_grid_starts_over(
        through, tmp_path):
    folder, lines = tmp_path / "partial", []

    def log_then_kill(line: str) -> None:
        if "checkpoint after 1 of 4" in line:
            raise Killed

    other = GridTraining(CONFIG, SEEDS, {"lam": [0.0, 3.0]})
    with pytest.raises(Killed):
        train_resumably(other, folder, every_s=1e-9, log=log_then_kill)

    runs = train_resumably(grid(), folder, every_s=0, log=lines.append)
    assert any("not resuming" in line and "set it aside" in line for line in lines), lines
    assert len(list(tmp_path.glob("partial-set-aside-*"))) == 1
    for key in through.history:
        np.testing.assert_array_equal(runs.history[key], through.history[key], key)


def test_an_interrupted_wait_for_a_save_is_not_reported_as_a_failure(caplog):
    """Ctrl-C while a grid waits for its checkpoint: orbax logs the interrupted wait as an
    ERROR with the KeyboardInterrupt's traceback (the save goes on and completes when the
    checkpoints close). ccrjax.run.checkpoint drops that record; any other error orbax
    logs still shows."""
    with caplog.at_level(logging.ERROR, logger="absl"):
        for error in (KeyboardInterrupt(), RuntimeError("disk full")):
            try:
                raise error
            except BaseException:
                absl_logging.exception("[wait_until_finished] Save Finalize thread failed.")
    assert [record.exc_info[0] for record in caplog.records] == [RuntimeError]

