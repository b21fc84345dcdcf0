"""The scripted proportional-derivative ("PID") controllers (:data:`CONTROLLERS`): they read only the 29-D observation
and have SB3's ``predict`` signature."""

from __future__ import annotations

from collections.abc import Sequence

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
#: End-effector target relative to the object's centre when grasping (m).
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
#: With ``regrasp``: distance (m) from the closed hand to the object beyond which the object counts as dropped (held,
#: it is within ~1 cm), and the largest vertical distance at which the gripper may close.
DROPPED_DISTANCE = 0.05
CLOSING_Z_TOLERANCE = 0.03
#: Hand orientation: pointing down, the fingers closing along the world y axis (following an upright cylinder's yaw
#: would flip the hand at +-pi/4).
HAND_ORIENTATION = np.array([1.0, 0.0, 0.0, 0.0])  # xyzw, rotation of pi about x
#: The ``yaw`` option: ``"fixed"`` (``HAND_ORIENTATION``), ``"random"`` (each attempt) or ``"aligned"``.
YAW_MODES = ("fixed", "random", "aligned")
#: Half-width (rad) of the hand's yaws around ``HAND_ORIENTATION``'s: the fingers are alike, so a half turn covers all.
YAW_HALF_RANGE = np.pi / 2
#: Largest difference (rad) between the hand's yaw and the attempt's with which the hand descends.
YAW_TOLERANCE = 0.05
#: Largest lead (rad) of the hand's yaw target over its observed yaw (asked for a half turn at once, the inverse
#: kinematics sweeps the hand down through the tray); a lead of 0.3 regrasped worse (random yaw, PandaForce-v0, 40
#: episodes in delta actions: 0.10 against 0.175).
MAX_YAW_STEP = 0.15
#: Height (m) of the hand above the object's centre below which it does not turn (open fingers would sweep the object).
TURN_CLEARANCE = 0.08
#: Tilt (rad) of the object's axis from the vertical beyond which the aligned yaw counts the cylinder as lying.
LYING_TILT = np.pi / 4
#: How far (rad) beyond the half turn the aligned yaw may go to spare the hand a half turn (:meth:`PDController._follow`).
YAW_HYSTERESIS = 0.2
#: The controllers' names (evaluation, the benchmark's rows, behaviour policies) and the keywords of each.
CONTROLLERS = {
    "pid": {},
    "pid-regrasp": {"regrasp": True},
    "pid-regrasp-yaw": {"regrasp": True, "yaw": "random"},
    "pid-regrasp-aligned": {"regrasp": True, "yaw": "aligned"},
}
#: Reference controllers (the benchmark's ceiling), never a source of training data.
REFERENCE_CONTROLLERS = ("pid-regrasp-aligned",)
#: The controllers whose runs are behaviour data: all but the references.
BEHAVIOUR_CONTROLLERS = tuple(name for name in CONTROLLERS if name not in REFERENCE_CONTROLLERS)


def _multiply(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The Hamilton product of two xyzw quaternions: the rotation ``second``, then ``first``."""
    x1, y1, z1, w1 = first
    x2, y2, z2, w2 = second
    return np.array(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ]
    )


def _axis(quaternion: np.ndarray, index: int) -> np.ndarray:
    """The world direction of the local y (``index`` 1) or z (2) axis of the frame of an xyzw quaternion."""
    x, y, z, w = quaternion / np.linalg.norm(quaternion)
    if index == 1:
        return np.array([2 * (x * y - z * w), 1 - 2 * (x * x + z * z), 2 * (y * z + x * w)])
    return np.array([2 * (x * z + y * w), 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)])


def _angle(start: np.ndarray, end: np.ndarray) -> float:
    """The angle (rad, in [-pi, pi]) about the world z axis from the horizontal part of ``start`` to that of ``end``."""
    return float(np.arctan2(start[0] * end[1] - start[1] * end[0], start[0] * end[0] + start[1] * end[1]))


def _half_turn(angle: float) -> float:
    """``angle`` (rad) plus the multiple of pi that puts it in [-pi/2, pi/2)."""
    return float((angle + np.pi / 2) % np.pi - np.pi / 2)


def hand_orientation(yaw: float) -> np.ndarray:
    """``HAND_ORIENTATION`` turned by ``yaw`` (rad) about the world z axis (xyzw)."""
    return _multiply(np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]), HAND_ORIENTATION)


#: The direction along which the fingers close with ``HAND_ORIENTATION`` (the hand's y axis; world -y).
CLOSING_DIRECTION = _axis(HAND_ORIENTATION, 1)


def hand_yaw(orientation: np.ndarray) -> float:
    """The yaw (rad, in [-pi, pi]) of the hand of xyzw ``orientation`` relative to ``HAND_ORIENTATION``."""
    return _angle(CLOSING_DIRECTION, _axis(orientation, 1))


def aligned_yaw(object_orientation: np.ndarray) -> float:
    """The yaw (rad, in [-pi/2, pi/2)) relative to ``HAND_ORIENTATION`` with which the fingers close across the axis of
    a lying cylinder of xyzw ``object_orientation``; 0 for an upright one (tilted less than ``LYING_TILT``)."""
    axis = _axis(object_orientation, 2)
    if abs(axis[2]) > np.cos(LYING_TILT):
        return 0.0
    across = np.array([-axis[1], axis[0], 0.0])  # the horizontal direction across the axis
    return _half_turn(_angle(CLOSING_DIRECTION, across))


#: Largest horizontal and vertical distance (m) from the object to the fingers' midpoint of a closing on it.
CLOSING_REACH = 0.05


def closing_angle(observation: np.ndarray) -> float | None:
    """The angle (degrees, in [0, 90]) seen from above between the hand's closing direction and a lying cylinder's
    axis in a 29-D observation (90: across it, what grasps); ``None`` for an upright cylinder."""
    observation = np.asarray(observation, dtype=np.float64)
    axis = _axis(observation[OBSERVATION_SLICES["object_orientation"]], 2)
    if abs(axis[2]) > np.cos(LYING_TILT):
        return None
    angle = abs(_angle(_axis(observation[OBSERVATION_SLICES["ee_orientation"]], 1), axis))
    return float(np.degrees(min(angle, np.pi - angle)))


def closing_steps(observations: np.ndarray) -> np.ndarray:
    """The steps of an episode (observations of shape (T, 29), in order) at which open fingers begin to close on the
    object: step ``t`` where the fingers are open (at least ``GRIPPER_OPEN_WIDTH`` less 5 mm apart) and at ``t + 1``
    no longer are, the point between them within ``CLOSING_REACH`` of the object."""
    observations = np.asarray(observations, dtype=np.float64)
    widths = observations[:, OBSERVATION_SLICES["joint_positions"]][:, -len(FINGER_JOINTS) :].sum(axis=1)
    offsets = observations[:, OBSERVATION_SLICES["finger_offsets"]].reshape(len(observations), 2, 3).mean(axis=1)
    near = (np.linalg.norm(offsets[:, :2], axis=1) < CLOSING_REACH) & (np.abs(offsets[:, 2]) < CLOSING_REACH)
    is_open = widths >= GRIPPER_OPEN_WIDTH - 0.005
    return np.flatnonzero(is_open[:-1] & ~is_open[1:] & near[1:])


def closing_angles(observations: np.ndarray) -> list[float | None]:
    """:func:`closing_angle` at each of an episode's :func:`closing_steps`: the angle as the closing began."""
    observations = np.asarray(observations, dtype=np.float64)
    return [closing_angle(observations[step]) for step in closing_steps(observations)]


class PDController:
    """End-effector proportional control with inverse kinematics (on a simulator of its own) to the 9 joint targets.

    The phase is read from the observation: with the gripper open it moves above the object, descends, and closes once
    aligned; once the fingers have closed to the object's width it lifts to ``LIFT_HEIGHT``. With ``regrasp`` a closed
    hand more than ``DROPPED_DISTANCE`` from the object reopens and starts over. In ``"delta"`` mode the gripper's
    actions are +1 (open) or -1 (close). The thesis's PID's derivative term is a second proportional one: both are
    ``kp``.

    The hand points down. With ``yaw="fixed"`` its yaw is ``HAND_ORIENTATION``'s and the controller is memoryless;
    otherwise each grasp attempt has a yaw of its own, kept in ``predict``'s ``state``: ``"random"`` draws it from
    [-pi/2, pi/2), ``"aligned"`` (a reference) closes the fingers across a lying cylinder's axis (:func:`aligned_yaw`).
    The hand turns while it hovers, at most ``MAX_YAW_STEP`` ahead of its observed yaw, and descends only once within
    ``YAW_TOLERANCE`` of the attempt's yaw.

    :param action_mode: the action mode of the env it drives, ``"absolute"`` or ``"delta"``.
    :param config: the env's configuration (object size, delta limits); the defaults if omitted.
    :param kp: proportional gain on the end-effector position error.
    :param max_step: largest end-effector move per step and axis (m).
    :param regrasp: reopen and grasp again when the closed hand has lost the object.
    :param yaw: the hand's yaw at each grasp attempt, one of :data:`YAW_MODES`.
    :param seed: seed of the ``"random"`` yaw's draws (see :meth:`seed`).
    """

    def __init__(
        self,
        action_mode: str = "absolute",
        config: GraspConfig | None = None,
        kp: float = KP,
        max_step: float = MAX_STEP,
        regrasp: bool = False,
        yaw: str = "fixed",
        seed: int | Sequence[int] | np.random.Generator | None = None,
    ) -> None:
        if yaw not in YAW_MODES:
            raise ValueError(f"yaw must be one of {YAW_MODES}, got {yaw!r}")
        self.config = config or GraspConfig()
        self.kp = kp
        self.max_step = max_step
        self.regrasp = regrasp
        self.yaw = yaw
        self.seed(seed)
        self._sim = Simulator(self.config.sim_timestep)
        self.robot = Panda(self._sim, self.config, action_mode)
        self._closed_width = 2 * self.config.object_radius + CLOSED_MARGIN

    @classmethod
    def for_env(cls, env, **kwargs) -> PDController:
        """A controller matching ``env``'s action mode and configuration (a gymnasium env, wrapped or not)."""
        unwrapped = env.unwrapped
        return cls(unwrapped.action_mode, unwrapped.config, **kwargs)

    def seed(self, seed: int | Sequence[int] | np.random.Generator | None = None) -> None:
        """Seed the ``"random"`` yaw's draws: a generator as it is; a seed (as ``numpy.random.SeedSequence`` takes)
        gives a child of its sequence, so the draws do not repeat an env's reset with the same seed; ``None``: fresh
        entropy."""
        if isinstance(seed, np.random.Generator):
            self.rng = seed
        else:
            self.rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])

    def parameters(self) -> dict[str, float | str | list[float]]:
        """The controller's gains and thresholds (recorded in the datasets it collects)."""
        parameters = {
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
        if self.yaw == "random":
            parameters.update(
                yaw="random: uniform on yaw_range around hand_orientation's yaw, drawn at each grasp attempt",
                yaw_range=[-YAW_HALF_RANGE, YAW_HALF_RANGE],
                yaw_seed="PDController.seed(seed): numpy.random.default_rng(numpy.random.SeedSequence(seed).spawn(1)[0])",
            )
        elif self.yaw == "aligned":
            parameters.update(
                yaw="aligned: fingers across a lying cylinder's axis", lying_tilt=LYING_TILT, yaw_hysteresis=YAW_HYSTERESIS
            )
        if self.yaw != "fixed":
            parameters.update(yaw_tolerance=YAW_TOLERANCE, max_yaw_step=MAX_YAW_STEP, turn_clearance=TURN_CLEARANCE)
        return parameters

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """The float32 action for one observation (shape (29,)) or a batch (shape (n, 29)), SB3-style, and the state:
        ``state`` unchanged for the fixed yaw, else each observation's attempt yaw (rad) and whether its hand counted
        the object as dropped (pass it back, with ``episode_start`` as SB3's ``evaluate_policy`` does)."""
        observation = np.asarray(observation, dtype=np.float64)
        batch = observation.reshape(-1, observation.shape[-1])
        if self.yaw == "fixed":
            actions = np.stack([self._act(obs, None)[0] for obs in batch]).astype(np.float32)
            return (actions[0] if observation.ndim == 1 else actions), state
        if state is None:
            yaws, dropped, starts = np.zeros(len(batch)), np.zeros(len(batch), dtype=bool), np.ones(len(batch), dtype=bool)
        else:
            yaws, dropped = np.array(state[0], dtype=np.float64), np.array(state[1], dtype=bool)
            starts = np.zeros(len(batch), dtype=bool) if episode_start is None else np.asarray(episode_start, dtype=bool)
            starts = np.broadcast_to(starts.reshape(-1), (len(batch),))
        actions = []
        for index, obs in enumerate(batch):
            action, yaws[index], dropped[index] = self._act(obs, (yaws[index], dropped[index], starts[index]))
            actions.append(action)
        actions = np.stack(actions).astype(np.float32)
        return (actions[0] if observation.ndim == 1 else actions), (yaws, dropped)

    def _act(self, observation: np.ndarray, attempt: tuple[float, bool, bool] | None) -> tuple[np.ndarray, float, bool]:
        """The action for one observation, the attempt's yaw (rad) and whether the object counts as dropped;
        ``attempt``: ``None`` for the fixed yaw, else the yaw so far, whether the object counted as dropped at the
        previous step and whether this is an episode's first step."""
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
        holding = not dropped and width < self._closed_width
        at_grasp = closing or (xy_error < GRASP_XY_TOLERANCE and abs(error[2]) < GRASP_Z_TOLERANCE)
        yaw, command, turned = 0.0, 0.0, True
        if attempt is not None:
            yaw, was_dropped, start = attempt
            current = hand_yaw(observation[OBSERVATION_SLICES["ee_orientation"]])
            if self.yaw == "random" and (start or (dropped and not was_dropped)):  # a new grasp attempt
                yaw = self.rng.uniform(-YAW_HALF_RANGE, YAW_HALF_RANGE)
            if self.yaw == "aligned" and not (holding or at_grasp):  # the object is free: follow its axis
                yaw = self._follow(aligned_yaw(observation[OBSERVATION_SLICES["object_orientation"]]), current)
            # Yaws stay within the half turn and the hysteresis, far from +-pi: their plain difference is the turn.
            turned = abs(yaw - current) < YAW_TOLERANCE
            command = current  # held while the fingers reopen after a drop, and close above the object
            if not dropped and (turned or ee[2] - obj[2] > TURN_CLEARANCE):
                command += np.clip(yaw - current, -MAX_YAW_STEP, MAX_YAW_STEP)
        if dropped:
            target, fingers = obj + np.array([0.0, 0.0, HOVER_HEIGHT]), GRIPPER_OPEN_WIDTH / 2
        elif holding:
            target, fingers = np.array([ee[0], ee[1], LIFT_HEIGHT]), 0.0
        elif at_grasp:
            target, fingers = grasp_point, 0.0
        elif xy_error < COARSE_XY_TOLERANCE and turned:
            target, fingers = grasp_point, GRIPPER_OPEN_WIDTH / 2
        else:
            target, fingers = obj + np.array([0.0, 0.0, HOVER_HEIGHT]), GRIPPER_OPEN_WIDTH / 2
        step = np.clip(self.kp * (target - ee), -self.max_step, self.max_step)
        orientation = HAND_ORIENTATION if attempt is None else hand_orientation(command)
        targets = self.robot.inverse_kinematics(joints, ee + step, orientation)
        targets[-len(FINGER_JOINTS) :] = fingers
        action = self.robot.action_from_targets(targets, joints)
        if self.robot.action_mode == "delta":
            # The gripper is commanded fully open or fully closed (+1 / -1), not "hold where you are" (0), which a
            # learned policy imitates with a small bias that closes the fingers step by step before the grasp.
            action[-len(FINGER_JOINTS) :] = 1.0 if fingers > 0 else -1.0
        return action, yaw, dropped

    @staticmethod
    def _follow(target: float, hand: float) -> float:
        """``target`` (rad, in [-pi/2, pi/2)) or the yaw a half turn from it, whichever is nearer the ``hand``'s yaw,
        within ``YAW_HYSTERESIS`` of the half turn's ends."""
        nearest = hand + _half_turn(target - hand)
        return nearest if abs(nearest) <= YAW_HALF_RANGE + YAW_HYSTERESIS else target

    def close(self) -> None:
        """Release the controller's own simulator."""
        self._sim.close()
