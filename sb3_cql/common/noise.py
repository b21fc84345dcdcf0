"""Temporally correlated exploration noise for online fine-tuning, as SB3 ``ActionNoise``: one draw held for a whole
action chunk (:class:`HeldActionNoise`), and pink noise (``pink-noise-rl``'s ``PinkActionNoise``, Eberhard et al.,
"Pink Noise Is All You Need", ICLR 2023) made reproducible (:func:`pink_action_noise`).

In delta actions a step moves a joint target by at most ``arm_max_delta`` (0.05 rad) times the action: N(0, 0.1) drawn
afresh each step moves the wrist by about 0.1 x 0.05 x sqrt(100) = 0.05 rad (3 degrees) in 100 steps, where turning
the hand to a fallen cylinder takes up to 90 degrees. Noise that keeps its sign for several steps moves it further:
a draw held for ``hold`` steps by ``hold`` times as much per draw (sqrt(hold) times as far over 100 steps), pink noise
further still (its power is concentrated at low frequencies).
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.noise import ActionNoise

__all__ = ["HeldActionNoise", "pink_action_noise"]


class HeldActionNoise(ActionNoise):
    """Each draw of ``noise`` repeated for ``hold`` consecutive calls: with ``hold`` the length of an action chunk,
    one exploration draw per chunk (the chunk's actions all moved by the same offset). :meth:`reset` (SB3 calls it when
    an episode ends, as a chunked policy starts a new chunk) makes the next call draw again, and resets ``noise``.

    :param noise: the noise drawn once per ``hold`` calls (SB3's ``NormalActionNoise``, ...).
    :param hold: calls each draw is held for (1: ``noise`` itself).
    """

    def __init__(self, noise: ActionNoise, hold: int) -> None:
        if hold < 1:
            raise ValueError(f"hold must be >= 1, got {hold}")
        super().__init__()
        self.noise, self.hold = noise, hold
        self._draw: np.ndarray | None = None
        self._calls = 0

    def __call__(self) -> np.ndarray:
        if self._draw is None or self._calls % self.hold == 0:
            self._draw = np.asarray(self.noise())
        self._calls += 1
        return self._draw.copy()

    def reset(self) -> None:
        self.noise.reset()
        self._draw, self._calls = None, 0

    def __repr__(self) -> str:
        return f"HeldActionNoise({self.noise!r}, hold={self.hold})"


def pink_action_noise(sigma: float, action_dim: int, seq_len: int, seed: int | None = None) -> ActionNoise:
    """``pink-noise-rl``'s ``PinkActionNoise`` (pink noise of scale ``sigma`` on each of ``action_dim`` dimensions,
    sampled in sequences of ``seq_len`` steps: an episode's length) with a random generator seeded by ``seed``: the
    package's default generator is unseeded, so a run with a seed would not repeat.

    :param sigma: the noise's standard deviation per dimension (in the scaled action space, [-1, 1]).
    :param action_dim: dimensions of the action space.
    :param seq_len: steps of one pink-noise sequence (a new one is drawn when it is used up).
    :param seed: seed of the noise's generator.
    """
    if not sigma >= 0 or action_dim < 1 or seq_len < 1:
        raise ValueError(
            f"pink noise needs sigma >= 0, action_dim >= 1 and seq_len >= 1, got {sigma}, {action_dim}, {seq_len}"
        )
    from pink import PinkActionNoise

    return PinkActionNoise(sigma, seq_len, action_dim, rng=np.random.default_rng(seed))
