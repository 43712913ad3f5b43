"""Reward transforms between the environment and the learner: the Transform protocol, the
plain and pessimistic baselines (:mod:`ccrjax.transforms.base`) and CCR
(:mod:`ccrjax.transforms.ccr`). A learner never knows which one it trains under."""

from ccrjax.transforms.base import Pessimistic, Plain, Transform
from ccrjax.transforms.ccr import CCR, CCRConfig, CCRState

VARIANTS = ("plain", "pessimistic", "ccr")

__all__ = ["CCR", "VARIANTS", "CCRConfig", "CCRState", "Pessimistic", "Plain", "Transform"]
