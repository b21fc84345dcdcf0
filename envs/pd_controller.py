"""The scripted proportional-derivative ("PID") controller that generates the behaviour data.

It reads only the 29-D observation and has SB3's ``predict`` signature, so
``stable_baselines3.common.evaluation.evaluate_policy(PDController(), env)`` works.
"""

from __future__ import annotations

import numpy as np

from envs.config import GraspConfig
from envs.panda_env import OBSERVATION_SLICES
from envs.robot import FINGER_JOINTS, GRIPPER_OPEN_WIDTH, Panda
from envs.simulator import Simulator

#: Proportional gain on the end-effector position error, per step.
KP = 0.5
#: Largest end-effector move per step, per axis (m).
MAX_STEP = 0.015
#: Height above the object's centre at which the hand aligns before descending (m).
HOVER_HEIGHT = 0.12
#: End-effector target relative to the object's centre when grasping (m): the fingertip pads cover the
#: upper half of the cylinder.
GRASP_OFFSET = 0.0
#: Horizontal alignment needed to start the descent (m).
COARSE_XY_TOLERANCE = 0.02
#: Alignment needed to close the gripper, horizontal and vertical (m).
GRASP_XY_TOLERANCE = 0.01
GRASP_Z_TOLERANCE = 0.01
#: Opening (m) beyond the object's diameter below which the gripper counts as closed on the object.
CLOSED_MARGIN = 0.004
#: End-effector height the lift aims for (m), above the 0.4 m success height.
LIFT_HEIGHT = 0.5
#: With ``regrasp``: distance (m) between the closed hand and the object's centre beyond which the object counts as
#: dropped (held, it is within ~1 cm), and the largest vertical distance at which the gripper may close.
DROPPED_DISTANCE = 0.05
CLOSING_Z_TOLERANCE = 0.03
#: Hand orientation: pointing down with a fixed yaw (a cylinder needs no yaw tracking, and following the
#: object's yaw flips the hand at +-pi/4).
HAND_ORIENTATION = np.array([1.0, 0.0, 0.0, 0.0])  # xyzw, rotation of pi about x
#: The controller's names (behaviour policies, evaluation, the benchmark's rows) and the keywords of each.
CONTROLLERS = {"pid": {}, "pid-regrasp": {"regrasp": True}}


class PDController:
    """End-effector proportional control with inverse kinematics to the 9 joint targets.

    Memoryless: the phase is read from the observation. With the gripper open it moves above the object,
    descends to it, and closes once aligned within the grasp tolerances; once the fingers have closed to
    the object's width it lifts to ``LIFT_HEIGHT``. By default a dropped object is not regrasped (the fingers
    stay closed), as in the thesis's controller; with ``regrasp`` a closed hand more than ``DROPPED_DISTANCE``
    from the object reopens and starts over above it (PandaForce-v0's knock-out). In ``"delta"`` mode the
    gripper's actions are +1 (open) or -1 (close). The "derivative" of the thesis's PID is ``k_d * error / dt``, a
    second proportional term: here both are the single gain ``kp``.

    Inverse kinematics runs on a robot in a DIRECT simulator of the controller's own, reset to the observed
    joints, so it never disturbs the environment's simulation.

    :param action_mode: the action mode of the env it drives, ``"absolute"`` or ``"delta"``.
    :param config: the env's configuration (object size, delta limits); the defaults if omitted.
    :param kp: proportional gain on the end-effector position error.
    :param max_step: largest end-effector move per step and axis (m).
    :param regrasp: reopen and grasp again when the closed hand has lost the object.
    """

    def __init__(
        self,
        action_mode: str = "absolute",
        config: GraspConfig | None = None,
        kp: float = KP,
        max_step: float = MAX_STEP,
        regrasp: bool = False,
    ) -> None:
        self.config = config or GraspConfig()
        self.kp = kp
        self.max_step = max_step
        self.regrasp = regrasp
        self._sim = Simulator(self.config.sim_timestep)
        self.robot = Panda(self._sim, self.config, action_mode)
        self._closed_width = 2 * self.config.object_radius + CLOSED_MARGIN

    @classmethod
    def for_env(cls, env, **kwargs) -> PDController:
        """A controller matching ``env``'s action mode and configuration (a gymnasium env, wrapped or not)."""
        unwrapped = env.unwrapped
        return cls(unwrapped.action_mode, unwrapped.config, **kwargs)

    def parameters(self) -> dict[str, float | list[float]]:
        """The controller's gains and thresholds (recorded in the datasets it collects)."""
        return {
            "kp": self.kp,
            "max_step": self.max_step,
            "hover_height": HOVER_HEIGHT,
            "grasp_offset": GRASP_OFFSET,
            "coarse_xy_tolerance": COARSE_XY_TOLERANCE,
            "grasp_xy_tolerance": GRASP_XY_TOLERANCE,
            "grasp_z_tolerance": GRASP_Z_TOLERANCE,
            "closed_margin": CLOSED_MARGIN,
            "lift_height": LIFT_HEIGHT,
            "hand_orientation": HAND_ORIENTATION.tolist(),
            **({"dropped_distance": DROPPED_DISTANCE, "closing_z_tolerance": CLOSING_Z_TOLERANCE} if self.regrasp else {}),
        }

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """The action for one observation (shape (29,)) or a batch (shape (n, 29)), SB3-style.

        :return: the action(s) as float32 and ``state`` unchanged (the controller is memoryless).
        """
        observation = np.asarray(observation, dtype=np.float64)
        if observation.ndim == 1:
            return self._act(observation).astype(np.float32), state
        return np.stack([self._act(obs) for obs in observation]).astype(np.float32), state

    def _act(self, observation: np.ndarray) -> np.ndarray:
        joints = observation[OBSERVATION_SLICES["joint_positions"]]
        ee = observation[OBSERVATION_SLICES["ee_position"]]
        obj = observation[OBSERVATION_SLICES["object_position"]]
        width = joints[-2:].sum()
        grasp_point = obj + np.array([0.0, 0.0, GRASP_OFFSET])
        error = grasp_point - ee
        xy_error = np.abs(error[:2]).max()
        closing = width < GRIPPER_OPEN_WIDTH - 0.005 and xy_error < COARSE_XY_TOLERANCE
        if self.regrasp:  # a gripper reopening above the object is not closing on it
            closing = closing and abs(error[2]) < CLOSING_Z_TOLERANCE
        dropped = self.regrasp and width < self._closed_width and np.linalg.norm(error) > DROPPED_DISTANCE
        if dropped:
            target, fingers = obj + np.array([0.0, 0.0, HOVER_HEIGHT]), GRIPPER_OPEN_WIDTH / 2
        elif width < self._closed_width:
            target, fingers = np.array([ee[0], ee[1], LIFT_HEIGHT]), 0.0
        elif closing or (xy_error < GRASP_XY_TOLERANCE and abs(error[2]) < GRASP_Z_TOLERANCE):
            target, fingers = grasp_point, 0.0
        elif xy_error < COARSE_XY_TOLERANCE:
            target, fingers = grasp_point, GRIPPER_OPEN_WIDTH / 2
        else:
            target, fingers = obj + np.array([0.0, 0.0, HOVER_HEIGHT]), GRIPPER_OPEN_WIDTH / 2
        step = np.clip(self.kp * (target - ee), -self.max_step, self.max_step)
        targets = self.robot.inverse_kinematics(joints, ee + step, HAND_ORIENTATION)
        targets[-len(FINGER_JOINTS) :] = fingers
        action = self.robot.action_from_targets(targets, joints)
        if self.robot.action_mode == "delta":
            # The gripper is commanded fully open or fully closed (+1 / -1), not "hold where you are" (0), which a
            # learned policy imitates with a small bias that closes the fingers step by step before the grasp.
            action[-len(FINGER_JOINTS) :] = 1.0 if fingers > 0 else -1.0
        return action

    def close(self) -> None:
        """Release the controller's own simulator."""
        self._sim.close()
