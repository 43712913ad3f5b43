"""Reward transforms between the environment and the learner: the Transform protocol, the
plain and pessimistic baselines (:mod:`ccrjax.transforms.base`), CCR
(:mod:`ccrjax.transforms.ccr`) and its parts taken apart (:mod:`ccrjax.transforms.ccr.parts`).
A learner never knows which one it trains under."""

from ccrjax.transforms.base import Pessimistic, Plain, Transform
from ccrjax.transforms.ccr import (
    CCR,
    CCRConfig,
    CCRPerfect,
    CCRReward,
    CCRScores,
    CCRState,
    DangerFlags,
)

# The built-in variants (ccrjax.registry.transform_names() adds those registered elsewhere).
VARIANTS = ("plain", "pessimistic", "ccr", "ccr_scores", "ccr_reward", "ccr_perfect",
            "danger_flags")

__all__ = ["CCR", "VARIANTS", "CCRConfig", "CCRPerfect", "CCRReward", "CCRScores", "CCRState",
           "DangerFlags", "Pessimistic", "Plain", "Transform"]
