"""Every physical parameter and threshold of the grasping tasks, in one place (:class:`GraspConfig`). Units: metres,
kilograms, seconds, newtons, radians.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

Range = tuple[float, float]


class ConfigError(ValueError):
    """A physical parameter or threshold that is not a finite number, or is out of its range."""


#: The bounds of the fields that have one: ``(lowest, whether the lowest itself is allowed)``.
FIELD_BOUNDS = {
    "sim_timestep": (0.0, False), "substeps": (1, True), "arm_motor_force": (0.0, True),
    "finger_motor_force": (0.0, True), "finger_contact_stiffness": (0.0, False), "finger_contact_damping": (0.0, True),
    "arm_max_delta": (0.0, False), "finger_max_delta": (0.0, False), "object_radius": (0.0, False),
    "object_height": (0.0, False), "object_mass": (0.0, False), "object_lateral_friction": (0.0, True),
    "object_drop_height": (0.0, True), "force_magnitude": (0.0, True),
}  # fmt: skip
#: The fields that are pairs ``(low, high)`` or vectors, with their length.
FIELD_LENGTHS = {"object_x_range": 2, "object_y_range": 2, "object_yaw_range": 2, "gravity_range": 2,
                 "object_mass_range": 2, "object_friction_range": 2, "force_direction": 3}  # fmt: skip


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _check_field(name: str, value: Any) -> None:
    """:class:`ConfigError` unless the field ``name`` has a value the simulation can use."""
    if name == "randomize_physics":
        if not isinstance(value, (bool, np.bool_)):
            raise ConfigError(f"randomize_physics must be True or False, got {value!r}")
        return
    if name in FIELD_LENGTHS:
        length = FIELD_LENGTHS[name]
        if not isinstance(value, (tuple, list)) or len(value) != length or not all(map(_is_number, value)):
            raise ConfigError(f"{name} must be {length} numbers, got {value!r}")
        if not all(math.isfinite(v) for v in value):
            raise ConfigError(f"{name} must be finite numbers, got {value!r}")
        return
    if name == "substeps" and not (isinstance(value, numbers.Integral) and not isinstance(value, bool)):
        raise ConfigError(f"substeps must be an integer >= 1, got {value!r}")
    if not _is_number(value) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    if name in FIELD_BOUNDS:
        lowest, allowed = FIELD_BOUNDS[name]
        if value < lowest or (value == lowest and not allowed):
            raise ConfigError(f"{name} must be {'>=' if allowed else '>'} {lowest}, got {value!r}")


@dataclass(frozen=True)
class GraspConfig:
    """Physics and task parameters of the Panda grasping tasks (each a keyword of the envs; why each value:
    ``docs/tasks.md``; gravity, mass and friction: Table A.2 of the thesis).

    :param sim_timestep: PyBullet's internal time step (s).
    :param substeps: physics steps per environment step (4 of 1/240 s: 60 Hz control).
    :param gravity: gravity along world z (m/s^2).
    :param arm_motor_force: maximum torque of each of the 7 arm joint motors (N m).
    :param finger_motor_force: maximum force of each finger motor (N).
    :param finger_contact_stiffness: contact stiffness of the finger pads (N/m).
    :param finger_contact_damping: contact damping of the finger pads (N s/m).
    :param arm_max_delta: largest change of an arm joint target per step in ``"delta"`` action mode (rad).
    :param finger_max_delta: largest change of a finger target per step in ``"delta"`` action mode (m).
    :param object_radius: cylinder radius (m).
    :param object_height: cylinder height (m).
    :param object_mass: object mass (kg).
    :param object_lateral_friction: object lateral friction coefficient (Bullet multiplies it by the fingers' 1.0).
    :param object_x_range: range of the object's initial x in the robot base frame (m).
    :param object_y_range: range of the object's initial y (m).
    :param object_yaw_range: range of the object's initial yaw (rad).
    :param object_drop_height: height above the tray floor from which the object is dropped (m).
    :param success_height: height of the object's centre (world z, m) at which a held object completes the task.
    :param force_magnitude: magnitude of the one-time external force of PandaForce-v0 (N); 0 disables it.
    :param force_direction: direction of that force in the world frame (normalised internally).
    :param force_height: object height at which the force is applied, once, during one env step (m).
    :param randomize_physics: sample gravity, object mass and friction from the ranges below at every reset.
    :param gravity_range: gravity range (m/s^2) when ``randomize_physics``.
    :param object_mass_range: object mass range (kg) when ``randomize_physics``.
    :param object_friction_range: object lateral friction range when ``randomize_physics``.
    """

    sim_timestep: float = 1.0 / 240.0
    substeps: int = 4
    gravity: float = -10.0
    arm_motor_force: float = 100.0
    finger_motor_force: float = 60.0
    finger_contact_stiffness: float = 1.0e6
    finger_contact_damping: float = 3000.0
    arm_max_delta: float = 0.05
    finger_max_delta: float = 0.01
    object_radius: float = 0.02
    object_height: float = 0.08
    object_mass: float = 0.1
    object_lateral_friction: float = 0.1
    object_x_range: Range = (0.5, 0.7)
    object_y_range: Range = (-0.15, 0.15)
    object_yaw_range: Range = (-math.pi / 5, math.pi / 5)
    object_drop_height: float = 0.002
    success_height: float = 0.4
    force_magnitude: float = 0.0
    force_direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    force_height: float = 0.2
    randomize_physics: bool = False
    gravity_range: Range = (-20.0, 0.5)
    object_mass_range: Range = (0.01, 10.0)
    object_friction_range: Range = (0.01, 1.0)
    # Derived, not a keyword.
    control_timestep: float = field(init=False)

    def __post_init__(self) -> None:
        for item in fields(self):
            if item.init:
                _check_field(item.name, getattr(self, item.name))
        for name in ("object_x_range", "object_y_range", "object_yaw_range", "gravity_range", "object_mass_range",
                     "object_friction_range"):  # fmt: skip
            low, high = getattr(self, name)
            if not low <= high:
                raise ConfigError(f"{name} must be (low, high) with low <= high, got {(low, high)}")
            object.__setattr__(self, name, (float(low), float(high)))
        if self.object_mass_range[0] <= 0:
            raise ConfigError(f"object_mass_range must hold positive masses, got {self.object_mass_range}")
        if self.object_friction_range[0] < 0:
            raise ConfigError(f"object_friction_range must hold frictions >= 0, got {self.object_friction_range}")
        norm = math.sqrt(sum(c * c for c in self.force_direction))
        if norm == 0:
            raise ConfigError(f"force_direction must be a non-zero 3-vector, got {self.force_direction}")
        object.__setattr__(self, "force_direction", tuple(float(c) / norm for c in self.force_direction))
        object.__setattr__(self, "control_timestep", self.sim_timestep * self.substeps)

    @classmethod
    def keywords(cls) -> tuple[str, ...]:
        """The fields that are keywords of the environments (all but the derived ones)."""
        return tuple(item.name for item in fields(cls) if item.init)

    def to_kwargs(self) -> dict[str, Any]:
        """The keywords that rebuild this configuration (``GraspConfig(**config.to_kwargs())``)."""
        kwargs = asdict(self)
        del kwargs["control_timestep"]
        return kwargs
