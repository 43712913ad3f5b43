"""The learners: independent DDPG and MADDPG (:mod:`ccrjax.agents.ddpg`), MAAC
(:mod:`ccrjax.agents.maac`), the on-device replay buffer (:mod:`ccrjax.agents.replay`),
networks, and the :class:`Learner` protocol every learner implements
(:mod:`ccrjax.agents.types`)."""

from ccrjax.agents.ddpg import DDPG, DDPGConfig, DDPGState
from ccrjax.agents.maac import MAAC, MAACConfig, MAACState
from ccrjax.agents.replay import ReplayBuffer, add_episodes, init_replay, sample
from ccrjax.agents.types import Learner, Transition

# The built-in learners (ccrjax.registry.learner_names() adds those registered elsewhere).
ALGOS = ("iddpg", "maddpg", "maac")

__all__ = ["ALGOS", "DDPG", "MAAC", "DDPGConfig", "DDPGState", "Learner", "MAACConfig",
           "MAACState", "ReplayBuffer", "Transition", "add_episodes", "init_replay", "sample"]
