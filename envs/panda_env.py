"""The gymnasium environment joining the simulator, the Panda and the grasping task."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from envs.config import GraspConfig
from envs.robot import Panda
from envs.simulator import Simulator
from envs.task import GraspTask

#: Observation layout: name -> slice of the 29-D observation.
OBSERVATION_SLICES = {
    "joint_positions": slice(0, 9),
    "ee_position": slice(9, 12),
    "ee_orientation": slice(12, 16),
    "object_position": slice(16, 19),
    "object_orientation": slice(19, 23),
    "finger_offsets": slice(23, 29),
}
OBSERVATION_SIZE = 29
#: The keywords of the tasks besides the physics of :class:`~envs.config.GraspConfig`.
ENV_KEYWORDS = ("render_mode", "action_mode", "render_width", "render_height")


def check_keywords(kwargs: dict[str, Any]) -> None:
    """``TypeError`` naming the keywords of ``kwargs`` that the tasks do not take, and those they take."""
    unknown = sorted(set(kwargs) - {*ENV_KEYWORDS, *GraspConfig.keywords()})
    if unknown:
        raise TypeError(f"unknown keyword(s) {', '.join(unknown)}: the tasks take {', '.join(ENV_KEYWORDS)} and the "
                        f"physics of GraspConfig: {', '.join(GraspConfig.keywords())}")  # fmt: skip


class PandaGraspEnv(gym.Env):
    """A Franka Panda picking a cylinder out of a tray (thesis chapter 4).

    - Observation (29 float32, :data:`OBSERVATION_SLICES`): 9 joint positions, end-effector position and xyzw
      quaternion, object position and quaternion, the vector from the object to each finger.
    - Action (9): desired joint positions (``"absolute"``, the joint limits its bounds) or bounded joint-target
      changes in [-1, 1] (``"delta"``).
    - Reward: 1.0, terminating, on the step at which the object, held by both fingers, reaches ``success_height``.

    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"`` (PyBullet's GUI).
    :param action_mode: ``"absolute"`` or ``"delta"``.
    :param render_width: frame width (pixels).
    :param render_height: frame height (pixels).
    :param physics: any field of :class:`~envs.config.GraspConfig`; unknown keywords raise ``TypeError``.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 60}

    def __init__(
        self,
        render_mode: str | None = None,
        action_mode: str = "absolute",
        render_width: int = 480,
        render_height: int = 360,
        **physics: Any,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        check_keywords(physics)
        self.config = GraspConfig(**physics)
        self.render_mode = render_mode
        self.action_mode = action_mode
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.config.control_timestep)}
        self.sim = Simulator(self.config.sim_timestep, self.config.substeps, render_mode, render_width, render_height)
        self.robot = Panda(self.sim, self.config, action_mode)
        self.task = GraspTask(self.sim, self.robot, self.config)
        self._initial_state = self.sim.save_state()
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(OBSERVATION_SIZE,), dtype=np.float32)
        self.action_space = self.robot.action_space
        self._joint_positions = np.zeros(len(self.robot.lower_limits))
        self._object_height = 0.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        # Restoring the state saved at construction makes an episode independent of the previous ones.
        self.sim.restore_state(self._initial_state)
        physics = self.task.reset(self.np_random)
        self.robot.reset()
        return self._observe(), {"is_success": False, **physics}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {action.shape}")
        if not np.isfinite(action).all():
            raise ValueError(f"action must be finite, got {action}")
        self.robot.set_joint_targets(self.robot.targets_from_action(action, self._joint_positions))
        force_applied = self.task.before_step(self._object_height)
        self.sim.step()
        observation = self._observe()
        success = self.task.is_success(self._object_height)
        info = {"is_success": success, "force_applied": force_applied}
        return observation, float(success), success, False, info

    def _observe(self) -> np.ndarray:
        self._joint_positions = self.robot.joint_positions()
        ee_position, ee_orientation, left_finger, right_finger = self.robot.link_poses()
        object_position, object_orientation = self.task.object_pose()
        self._object_height = object_position[2]
        observation = np.empty(OBSERVATION_SIZE, dtype=np.float64)
        observation[:9] = self._joint_positions
        observation[9:23] = ee_position + ee_orientation + object_position + object_orientation
        observation[23:26] = left_finger
        observation[26:29] = right_finger
        observation[23:29] -= object_position * 2  # the tuple twice: subtracted from both fingers
        return observation.astype(np.float32)

    def render(self) -> np.ndarray | None:
        """An RGB frame in ``"rgb_array"`` mode; the GUI draws itself in ``"human"`` mode."""
        if self.render_mode == "rgb_array":
            return self.sim.render()
        return None

    def close(self) -> None:
        self.sim.close()
