"""Pictures of a trained team: one evaluation episode, drawn and animated.

The episode runs exactly as evaluation does (deterministic policy, the run's own
transform, so a CCR policy sees the shared emergency scores it was trained
with), in one fresh environment. Every robot's path has its own colour; under CCR
its steps are dotted in the colour of its CCR state (standby, sensing danger,
activated: the paper's blue, yellow and pink).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np

from ccrjax.run.folder import replacing
from ccrjax.training import TrainProgram, TrainState, make_env
from ccrjax.training.acting import compile_for, run_episode
from ccrjax.viz.record import (
    CCR_STATE_COLOURS,
    CCR_STATE_NAMES,
    DEFAULT_STATE_COLOURS,
    DEFAULT_STATE_NAMES,
    EpisodeRecord,
    episode_record,
)
from ccrjax.viz.render import animate_episode, draw_episode

# Key of the pictures' episode: far from the training keys (seed) and evaluation keys.
PICTURE_KEY = 0x9E3779B1


def unbroken(command: str) -> str:
    """``command`` with no-break spaces, so that a caption wrapped to the picture's width
    never splits it across lines."""
    return command.replace(" ", "\u00a0")


def record_trained_episode(program: TrainProgram, state: TrainState, key: jax.Array,
                           caption: str = "") -> EpisodeRecord:
    """One evaluation episode of ``state`` (one seed, no seed axis) in a fresh environment,
    deterministic policy, with every robot's danger at every step; ``caption`` names it."""
    env = make_env(program.config, 1)

    def rollout(state: TrainState, key: jax.Array):
        def greedy(obs, key):
            return program.learner.act(state.learner, obs, key, False)

        _, episode = run_episode(
            env, program.transform, state.transform, greedy, program.learner.discrete, key
        )
        return episode.position, episode.hazard, episode.danger, episode.info.get("ccr_state")

    position, hazard, danger, ccr_state = compile_for(rollout, (state, key))(state, key)
    if ccr_state is None:
        return episode_record(env, hazard, position, danger, 0, None, DEFAULT_STATE_NAMES,
                              DEFAULT_STATE_COLOURS, caption)
    # The reset's positions come before any transition: standby.
    steps = np.asarray(ccr_state)[..., 0].astype(np.int32)  # [T, N]
    states = np.concatenate([np.zeros_like(steps[:1]), steps])
    return episode_record(env, hazard, position, danger, 0, states, CCR_STATE_NAMES,
                          CCR_STATE_COLOURS, caption)


def write_episode_pictures(record: EpisodeRecord, folder: Path, stem: str = "episode"
                           ) -> tuple[Path, Path]:
    """``<folder>/<stem>.png`` and ``<stem>.gif``, each written whole then renamed in place."""
    png, gif = folder / f"{stem}.png", folder / f"{stem}.gif"
    for path, draw in ((png, draw_episode), (gif, animate_episode)):
        with replacing(path) as temporary:
            draw(record, temporary)
    return png, gif


def seed_slice(tree: Any, index: int) -> Any:
    """Seed ``index`` of a state whose leaves carry a leading seed axis."""
    return jax.tree_util.tree_map(lambda x: x[index], tree)
