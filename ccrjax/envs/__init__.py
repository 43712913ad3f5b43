"""The world the robots live in: particle physics, the emergency scenarios, the batched env.

* :mod:`ccrjax.envs.world`: the MPE's particle physics (contacts, integration) and the
  swept stop against solid rectangles;
* :mod:`ccrjax.envs.scenarios`: the layout and one module per emergency, by name;
* :mod:`ccrjax.envs.env`: :class:`EmergencyEnv`, thousands of environments as one pure
  ``reset``/``step`` (brax's ``Env``), registered in brax as ``ccr_<scenario>``.
"""

from ccrjax.envs.env import EmergencyEnv, WorldState, random_actions, registered_name
from ccrjax.envs.scenarios import SCENARIOS, Hazard, Layout, Scenario, make_scenario

__all__ = ["SCENARIOS", "EmergencyEnv", "Hazard", "Layout", "Scenario", "WorldState",
           "make_scenario", "random_actions", "registered_name"]
