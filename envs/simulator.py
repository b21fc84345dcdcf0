"""A thin wrapper owning one PyBullet physics client, so that many environments live in one process. It imports and
connects to PyBullet with the lines its C code prints then sent to ``os.devnull``.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator

import numpy as np

try:  # The C library's fflush: what C code prints may wait in its buffers (a pipe or a file is fully buffered).
    _fflush = ctypes.CDLL(None).fflush
except (AttributeError, OSError, TypeError):  # no process-wide C library handle (Windows)
    _fflush = None


def _flush_output() -> None:
    """Write out what Python and C hold in their stdout and stderr buffers."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed or replaced stream
            stream.flush()
    if _fflush is not None:
        _fflush(None)


@contextlib.contextmanager
def silenced(*fds: int) -> Iterator[None]:
    """Send what is written to the file descriptors ``fds`` (a closed one is left alone) to ``os.devnull`` while the
    block runs, C code's output included; the buffers are flushed before and after."""
    _flush_output()
    devnull = os.open(os.devnull, os.O_WRONLY)
    saved = []
    try:
        for fd in fds:
            try:
                saved.append((fd, os.dup(fd)))
            except OSError:  # a closed descriptor: nothing to silence
                continue
            os.dup2(devnull, fd)
        yield
    finally:
        _flush_output()
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
        os.close(devnull)


with silenced(1, 2):  # pybullet build time: ... (on stderr with PyBullet 3.2.7)
    import pybullet
    import pybullet_data
    from pybullet_utils.bullet_client import BulletClient


class _BulletClient(BulletClient):
    """PyBullet's client, whose finaliser also takes one that Ctrl-C cut short while it connected (no id yet)."""

    _client = -1


class Simulator:
    """One PyBullet world: a ``BulletClient`` (its GUI for ``render_mode="human"``, else DIRECT), its physics
    ``timestep`` (s), ``substeps`` a :meth:`step`, and a camera of :meth:`render` frames (pixels)."""

    def __init__(
        self,
        timestep: float,
        substeps: int = 1,
        render_mode: str | None = None,
        render_width: int = 480,
        render_height: int = 360,
    ) -> None:
        self.render_mode = render_mode
        mode = pybullet.GUI if render_mode == "human" else pybullet.DIRECT
        with silenced(1):  # argv[0]= (on stdout); in GUI mode, also the OpenGL details PyBullet prints
            self.client = _BulletClient(connection_mode=mode)
        self.client.setAdditionalSearchPath(pybullet_data.getDataPath())
        if render_mode == "human":
            self.client.configureDebugVisualizer(pybullet.COV_ENABLE_GUI, 0)
        # One call runs all substeps (a force applied before it acts throughout); deterministic pairs: exact restores.
        self.client.setPhysicsEngineParameter(
            fixedTimeStep=timestep * substeps, numSubSteps=substeps, deterministicOverlappingPairs=1
        )
        self.render_width = render_width
        self.render_height = render_height
        self._view = self.client.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=[0.45, 0.0, 0.15], distance=1.1, yaw=50.0, pitch=-30.0, roll=0.0, upAxisIndex=2
        )
        self._projection = self.client.computeProjectionMatrixFOV(
            fov=60.0, aspect=render_width / render_height, nearVal=0.05, farVal=5.0
        )
        # BulletClient resolves every attribute through inspect: bind the call made at every step once.
        self.step_simulation = self.client.stepSimulation

    @property
    def id(self) -> int:
        """PyBullet's id of this client."""
        return self.client._client

    def step(self) -> None:
        """Advance the world by one control step (``substeps`` physics steps)."""
        self.step_simulation()

    def save_state(self) -> int:
        """Save the whole world state in memory and return its id."""
        return self.client.saveState()

    def restore_state(self, state_id: int) -> None:
        """Restore a state saved by :meth:`save_state` (positions, velocities and contacts)."""
        self.client.restoreState(stateId=state_id)

    def render(self) -> np.ndarray:
        """An RGB frame (height x width x 3, uint8) from a fixed camera looking at the tray."""
        renderer = pybullet.ER_BULLET_HARDWARE_OPENGL if self.render_mode == "human" else pybullet.ER_TINY_RENDERER
        _, _, rgba, _, _ = self.client.getCameraImage(
            self.render_width, self.render_height, self._view, self._projection, renderer=renderer
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(self.render_height, self.render_width, 4)[:, :, :3]

    def close(self) -> None:
        """Disconnect the client (idempotent)."""
        if self.client._client >= 0:
            self.client.disconnect()
