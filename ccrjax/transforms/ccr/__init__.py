"""Collective Conditioned Reflex (CCR): learned dynamics, emergency scores, intrinsic reward.

One idea per module:

* :mod:`ccrjax.transforms.ccr.dynamics`: the polynomial physical model and its robust
  closed-form fit;
* :mod:`ccrjax.transforms.ccr.scores`: emergency scores, their rolling mean, what robots share;
* :mod:`ccrjax.transforms.ccr.intrinsic`: the paper's intrinsic reward;
* :mod:`ccrjax.transforms.ccr.transform`: all of it as a transform (:mod:`ccrjax.transforms.base`);
* :mod:`ccrjax.transforms.ccr.parts`: its parts alone, a perfect detector, shared danger flags.
"""

from ccrjax.transforms.ccr.dynamics import (
    DynamicsStatistics,
    accumulate,
    accumulate_features,
    command_vector,
    fit,
    init_coefficients,
    init_statistics,
    model_inputs,
    model_targets,
    num_features,
    polynomial_features,
    predict_state,
    predict_targets,
    robust_weight,
    squared_error,
)
from ccrjax.transforms.ccr.intrinsic import intrinsic_reward
from ccrjax.transforms.ccr.parts import CCRPerfect, CCRReward, CCRScores, DangerFlags
from ccrjax.transforms.ccr.scores import (
    ScoreWindow,
    emergency_score,
    init_window,
    push_score,
    shared_scores,
    smoothed_score,
)
from ccrjax.transforms.ccr.transform import (
    ACTIVATED,
    CCR,
    SENSING_DANGER,
    STANDBY,
    CCRConfig,
    CCREpisodeState,
    CCRState,
    EpisodeArrays,
)

__all__ = [
    "ACTIVATED",
    "CCR",
    "CCRConfig",
    "CCREpisodeState",
    "CCRPerfect",
    "CCRReward",
    "CCRScores",
    "CCRState",
    "DangerFlags",
    "DynamicsStatistics",
    "EpisodeArrays",
    "SENSING_DANGER",
    "STANDBY",
    "ScoreWindow",
    "accumulate",
    "accumulate_features",
    "command_vector",
    "emergency_score",
    "fit",
    "init_coefficients",
    "init_statistics",
    "init_window",
    "intrinsic_reward",
    "model_inputs",
    "model_targets",
    "num_features",
    "polynomial_features",
    "predict_state",
    "predict_targets",
    "push_score",
    "robust_weight",
    "shared_scores",
    "smoothed_score",
    "squared_error",
]
