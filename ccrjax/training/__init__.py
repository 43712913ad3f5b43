"""Training: a configuration (:mod:`ccrjax.training.config`), acting in episodes
(:mod:`ccrjax.training.acting`), the pure training program ``make_train(config).train(key)``
(:mod:`ccrjax.training.program`), and grids of runs in one sharded program
(:mod:`ccrjax.training.grid`)."""

from ccrjax.agents import ALGOS
from ccrjax.training.acting import Episode, episode_metrics, run_episode
from ccrjax.training.config import (
    LEARNING_STARTS,
    TrainConfig,
    config_from_dict,
    config_to_dict,
    default_budgets,
    make_env,
    make_learner,
    make_transform,
)
from ccrjax.training.program import NonFiniteTraining, TrainProgram, TrainState, make_train
from ccrjax.transforms import VARIANTS

__all__ = ["ALGOS", "LEARNING_STARTS", "VARIANTS", "Episode", "NonFiniteTraining",
           "TrainConfig", "TrainProgram", "TrainState", "config_from_dict", "config_to_dict",
           "default_budgets", "episode_metrics", "make_env", "make_learner", "make_train",
           "make_transform", "run_episode"]
