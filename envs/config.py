"""Every physical parameter and threshold of the grasping tasks, in one place.

:class:`GraspConfig` is the single home of the simulation constants (Table A.2 of the thesis for
gravity, mass and friction). Every field is also a keyword of the environments, so
``gymnasium.make("Panda-v0", object_mass=0.5)`` changes the object's mass and an unknown keyword
raises ``TypeError``. Units: metres, kilograms, seconds, newtons, radians.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

Range = tuple[float, float]


@dataclass(frozen=True)
class GraspConfig:
    """Physics and task parameters of the Panda grasping tasks.

    :param sim_timestep: PyBullet's internal time step (s). 1/240 s is PyBullet's default and keeps
        the 60 N finger grip on a 0.1 friction cylinder stable.
    :param substeps: physics steps per environment step. 4 substeps of 1/240 s give a 60 Hz control
        rate: the PD controller lifts the object in about 180 steps, well inside the 700-step limit,
        and each env step costs four physics steps, not more.
    :param gravity: gravity along world z (m/s^2).
    :param arm_motor_force: maximum torque of each of the 7 arm joint motors (N m).
    :param finger_motor_force: maximum force of each finger motor (N). The URDF's 20 N lets the
        low-friction cylinder slip.
    :param finger_contact_stiffness: contact stiffness of the finger pads (N/m). The URDF's 30,000 lets a
        60 N grip sink 1 cm into each side of the object, and the stored spring launches an object that
        slips out metres away; at 1e6 the pads sink 1.6 mm.
    :param finger_contact_damping: contact damping of the finger pads (N s/m).
    :param arm_max_delta: largest change of an arm joint target per step in ``"delta"`` action mode (rad).
    :param finger_max_delta: largest change of a finger target per step in ``"delta"`` action mode (m).
    :param object_radius: cylinder radius (m).
    :param object_height: cylinder height (m).
    :param object_mass: object mass (kg).
    :param object_lateral_friction: object lateral friction coefficient (the fingers' is 1.0, and
        Bullet multiplies the two).
    :param object_x_range: range of the object's initial x in the robot base frame (m).
    :param object_y_range: range of the object's initial y (m).
    :param object_yaw_range: range of the object's initial yaw (rad).
    :param object_drop_height: height above the tray floor from which the object is dropped (m).
    :param success_height: height of the object's centre (world z, m) at which a held object
        completes the task.
    :param force_magnitude: magnitude of the one-time external force of PandaForce-v0 (N); 0 disables it.
    :param force_direction: direction of that force in the world frame (normalised internally).
    :param force_height: object height at which the force is applied, once, during one env step (m).
    :param randomize_physics: sample gravity, object mass and friction from the ranges below at every
        reset (PandaPerturbed-v0).
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
        if self.sim_timestep <= 0 or self.substeps < 1:
            raise ValueError(f"sim_timestep must be > 0 and substeps >= 1, got {self.sim_timestep}, {self.substeps}")
        for name in ("object_x_range", "object_y_range", "object_yaw_range", "gravity_range", "object_mass_range",
                     "object_friction_range"):  # fmt: skip
            low, high = getattr(self, name)
            if not low <= high:
                raise ValueError(f"{name} must be (low, high) with low <= high, got {(low, high)}")
            object.__setattr__(self, name, (float(low), float(high)))
        if self.object_mass <= 0 or self.object_mass_range[0] <= 0:
            raise ValueError("object masses must be positive")
        if self.force_magnitude < 0:
            raise ValueError(f"force_magnitude must be >= 0, got {self.force_magnitude}")
        norm = math.sqrt(sum(c * c for c in self.force_direction))
        if len(self.force_direction) != 3 or norm == 0:
            raise ValueError(f"force_direction must be a non-zero 3-vector, got {self.force_direction}")
        object.__setattr__(self, "force_direction", tuple(float(c) / norm for c in self.force_direction))
        object.__setattr__(self, "control_timestep", self.sim_timestep * self.substeps)

    def to_kwargs(self) -> dict[str, Any]:
        """The keywords that rebuild this configuration (``GraspConfig(**config.to_kwargs())``)."""
        kwargs = asdict(self)
        del kwargs["control_timestep"]
        return kwargs
