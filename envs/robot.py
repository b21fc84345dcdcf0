"""The Franka Panda arm: joints, limits, motors, inverse kinematics and the two action modes."""

from __future__ import annotations

import numpy as np
import pybullet
from gymnasium import spaces

from envs.config import GraspConfig
from envs.simulator import Simulator

ARM_JOINTS = (0, 1, 2, 3, 4, 5, 6)
FINGER_JOINTS = (9, 10)
#: The 9 controlled joints, in observation and action order.
JOINTS = ARM_JOINTS + FINGER_JOINTS
FINGER_LINKS = (9, 10)
#: ``panda_grasptarget``: the point between the fingertips.
END_EFFECTOR_LINK = 11
#: Franka's "ready" pose with the gripper open: the hand points down above the robot's base.
HOME_JOINT_POSITIONS = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04, 0.04)
#: The finger opening (sum of both finger joints, m) when fully open.
GRIPPER_OPEN_WIDTH = 0.08
ACTION_MODES = ("absolute", "delta")


class Panda:
    """A fixed-base Panda (``franka_panda/panda.urdf``) in a :class:`Simulator`, driven by 9 joint targets (7 arm
    joints in rad, 2 finger joints in m): the action itself (``"absolute"``) or the joint positions plus the action in
    [-1, 1] times ``arm_max_delta`` / ``finger_max_delta`` (``"delta"``), clipped to the joint limits.
    """

    def __init__(self, sim: Simulator, config: GraspConfig, action_mode: str = "absolute") -> None:
        if action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
        self.sim = sim
        self.action_mode = action_mode
        client = sim.client
        self.body = client.loadURDF("franka_panda/panda.urdf", useFixedBase=True)
        infos = [client.getJointInfo(self.body, j) for j in JOINTS]
        self.lower_limits = np.array([info[8] for info in infos])
        self.upper_limits = np.array([info[9] for info in infos])
        n_arm = len(ARM_JOINTS)
        #: Maximum motor torque (N m) or force (N) of each controlled joint.
        self.motor_forces = [config.arm_motor_force] * n_arm + [config.finger_motor_force] * len(FINGER_JOINTS)
        self.max_delta = np.array([config.arm_max_delta] * n_arm + [config.finger_max_delta] * len(FINGER_JOINTS))
        self._client_id = sim.id
        # PyBullet ignores the URDF's joint velocity limits: they are passed to each motor (docs/tasks.md).
        self.max_velocities = [info[11] for info in infos]
        self._null_space = {
            "lowerLimits": self.lower_limits.tolist(),
            "upperLimits": self.upper_limits.tolist(),
            "jointRanges": (self.upper_limits - self.lower_limits).tolist(),
            "restPoses": list(HOME_JOINT_POSITIONS),
        }

    @property
    def action_space(self) -> spaces.Box:
        """The joint limits in ``"absolute"`` mode, [-1, 1]^9 in ``"delta"`` mode."""
        if self.action_mode == "absolute":
            return spaces.Box(self.lower_limits.astype(np.float32), self.upper_limits.astype(np.float32))
        return spaces.Box(-1.0, 1.0, shape=(len(JOINTS),), dtype=np.float32)

    def reset(self, joint_positions=HOME_JOINT_POSITIONS) -> None:
        """Teleport the joints to ``joint_positions`` at rest and hold them there."""
        self._teleport(joint_positions)
        self.set_joint_targets(np.asarray(joint_positions, dtype=np.float64))

    def _teleport(self, joint_positions) -> None:
        for joint, position in zip(JOINTS, joint_positions, strict=True):
            pybullet.resetJointState(self.body, joint, position, 0.0, physicsClientId=self._client_id)

    def set_joint_targets(self, targets: np.ndarray) -> None:
        """Send 9 joint targets (within the limits) to the position controllers."""
        for joint, target, force, max_velocity in zip(
            JOINTS, targets.tolist(), self.motor_forces, self.max_velocities, strict=True
        ):
            pybullet.setJointMotorControl2(
                self.body,
                joint,
                pybullet.POSITION_CONTROL,
                targetPosition=target,
                force=force,
                maxVelocity=max_velocity,
                physicsClientId=self._client_id,
            )

    def joint_positions(self) -> np.ndarray:
        """Positions of the 9 controlled joints (rad, m)."""
        states = pybullet.getJointStates(self.body, JOINTS, physicsClientId=self._client_id)
        return np.array([state[0] for state in states])

    def link_poses(self) -> tuple[tuple[float, ...], ...]:
        """End-effector position and xyzw quaternion, and the two fingers' centres of mass, in the world frame."""
        end_effector, left, right = pybullet.getLinkStates(
            self.body, (END_EFFECTOR_LINK, *FINGER_LINKS), physicsClientId=self._client_id
        )
        return end_effector[4], end_effector[5], left[0], right[0]

    def targets_from_action(self, action: np.ndarray, joint_positions: np.ndarray) -> np.ndarray:
        """Joint targets for ``action`` given the current ``joint_positions``, clipped to the limits."""
        if self.action_mode == "delta":
            action = joint_positions + np.clip(action, -1.0, 1.0) * self.max_delta
        return action.clip(self.lower_limits, self.upper_limits)

    def action_from_targets(self, targets: np.ndarray, joint_positions: np.ndarray) -> np.ndarray:
        """The action that best requests ``targets`` (:meth:`targets_from_action`'s inverse, saturating)."""
        targets = np.clip(targets, self.lower_limits, self.upper_limits)
        if self.action_mode == "delta":
            return np.clip((targets - joint_positions) / self.max_delta, -1.0, 1.0)
        return targets

    def inverse_kinematics(
        self, joint_positions: np.ndarray, position: np.ndarray, orientation: np.ndarray, iterations: int = 20
    ) -> np.ndarray:
        """Joint positions placing the end effector at ``position`` with xyzw ``orientation``, from
        ``joint_positions`` (it teleports the robot: call it on a simulator of its own)."""
        self._teleport(joint_positions)
        solution = pybullet.calculateInverseKinematics(
            self.body,
            END_EFFECTOR_LINK,
            position.tolist(),
            orientation.tolist(),
            **self._null_space,
            maxNumIterations=iterations,
            physicsClientId=self._client_id,
        )
        return np.array(solution)
