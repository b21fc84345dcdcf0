"""PyBullet grasping tasks for offline RL: a Franka Panda picks a cylinder out of a tray.

Importing this package registers the gymnasium ids in :data:`ENV_IDS`.
"""

import gymnasium

# First: envs.simulator imports PyBullet with its start-up message silenced (envs.robot and envs.task import it too).
from envs import simulator  # noqa: F401
from envs.config import GraspConfig
from envs.panda_env import OBSERVATION_SLICES, PandaGraspEnv
from envs.pd_controller import CONTROLLERS, PDController

#: The registered ids and the keywords that make each task (everything else is :class:`GraspConfig`'s default).
ENV_IDS = {
    "Panda-v0": {},
    # One downward push of 60 N for one step (1/60 s) at 0.2 m pulls the 0.1 kg cylinder out of the 60 N
    # grip and drops it back into the tray.
    "PandaForce-v0": {"force_magnitude": 60.0},
    "PandaPerturbed-v0": {"randomize_physics": True},
}
MAX_EPISODE_STEPS = 700

for _env_id, _kwargs in ENV_IDS.items():
    if _env_id not in gymnasium.registry:
        gymnasium.register(
            _env_id, entry_point="envs.panda_env:PandaGraspEnv", max_episode_steps=MAX_EPISODE_STEPS, kwargs=_kwargs
        )

__all__ = ["CONTROLLERS", "ENV_IDS", "MAX_EPISODE_STEPS", "OBSERVATION_SLICES", "GraspConfig", "PDController", "PandaGraspEnv"]
