"""The grasping task: the tray, the cylinder, success, the knock-out force and perturbed physics."""

from __future__ import annotations

from typing import Any

import numpy as np
import pybullet

from envs.config import GraspConfig
from envs.robot import FINGER_LINKS, Panda
from envs.simulator import Simulator

TRAY_POSITION = (0.6, 0.0, 0.0)
#: Height of the top of the tray's floor (m), measured on ``tray/traybox.urdf`` at ``TRAY_POSITION``.
TRAY_FLOOR_HEIGHT = 0.015


class GraspTask:
    """Pick the cylinder (dropped upright at a random position and yaw) out of the tray and lift it, held by both
    fingers, to ``success_height``; with ``force_magnitude``, a push for one step the first time it rises to
    ``force_height``; with ``randomize_physics``, the physics sampled at every reset. The scene is built in ``sim``.
    """

    def __init__(self, sim: Simulator, robot: Panda, config: GraspConfig) -> None:
        self.sim = sim
        self.robot = robot
        self.config = config
        client = sim.client
        client.loadURDF("plane.urdf")
        client.loadURDF("tray/traybox.urdf", TRAY_POSITION)
        radius, height = config.object_radius, config.object_height
        collision = client.createCollisionShape(pybullet.GEOM_CYLINDER, radius=radius, height=height)
        visual = client.createVisualShape(pybullet.GEOM_CYLINDER, radius=radius, length=height, rgbaColor=[0.9, 0.2, 0.1, 1])
        self.object = client.createMultiBody(
            config.object_mass, collision, visual, [TRAY_POSITION[0], 0.0, 0.2], useMaximalCoordinates=True
        )
        # Continuous collision detection: a knocked or flung cylinder must not tunnel through the tray floor.
        client.changeDynamics(self.object, -1, ccdSweptSphereRadius=0.9 * radius)
        self.physics: dict[str, float] = {}
        self._force_applied = False
        self._client_id = sim.id

    def reset(self, np_random: np.random.Generator) -> dict[str, Any]:
        """Drop the object at a random pose and set this episode's physics (returned as a dict)."""
        config, client = self.config, self.sim.client
        x = np_random.uniform(*config.object_x_range)
        y = np_random.uniform(*config.object_y_range)
        yaw = np_random.uniform(*config.object_yaw_range)
        if config.randomize_physics:
            gravity = np_random.uniform(*config.gravity_range)
            mass = np_random.uniform(*config.object_mass_range)
            friction = np_random.uniform(*config.object_friction_range)
        else:
            gravity, mass, friction = config.gravity, config.object_mass, config.object_lateral_friction
        z = TRAY_FLOOR_HEIGHT + config.object_height / 2 + config.object_drop_height
        client.resetBasePositionAndOrientation(self.object, [x, y, z], client.getQuaternionFromEuler([0.0, 0.0, yaw]))
        client.resetBaseVelocity(self.object, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        radius, height = config.object_radius, config.object_height
        side_inertia = mass * (3 * radius**2 + height**2) / 12
        client.changeDynamics(
            self.object,
            -1,
            mass=mass,
            lateralFriction=friction,
            localInertiaDiagonal=[side_inertia, side_inertia, mass * radius**2 / 2],
        )
        client.setGravity(0.0, 0.0, gravity)
        self._force_applied = False
        self.physics = {"gravity": gravity, "object_mass": mass, "object_lateral_friction": friction}
        return dict(self.physics)

    def object_pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """Object position (m) and orientation quaternion (xyzw) in the world frame."""
        return pybullet.getBasePositionAndOrientation(self.object, physicsClientId=self._client_id)

    def before_step(self, object_height: float) -> bool:
        """Apply the one-time knock-out force, before a step, if the object has reached ``force_height``; whether
        it was applied now."""
        config = self.config
        if self._force_applied or config.force_magnitude == 0 or object_height < config.force_height:
            return False
        position, _ = self.object_pose()
        force = [config.force_magnitude * c for c in config.force_direction]
        pybullet.applyExternalForce(self.object, -1, force, position, pybullet.WORLD_FRAME, physicsClientId=self._client_id)
        self._force_applied = True
        return True

    def is_held(self) -> bool:
        """Whether the object touches both fingers."""
        return all(
            pybullet.getContactPoints(self.robot.body, self.object, finger, -1, physicsClientId=self._client_id)
            for finger in FINGER_LINKS
        )

    def is_success(self, object_height: float) -> bool:
        """The object's centre is at ``success_height`` or above and both fingers hold it."""
        return bool(object_height >= self.config.success_height) and self.is_held()
