"""Temporally correlated exploration noise for online fine-tuning, as SB3 ``ActionNoise``: one draw held for a whole
action chunk (:class:`HeldActionNoise`), and pink noise (Eberhard et al., ICLR 2023) made reproducible
(:func:`pink_action_noise`). N(0, 0.1) drawn afresh each step turns the wrist by about 3 degrees in 100 delta
actions, where a fallen cylinder takes up to 90: noise that keeps its sign moves it further.
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.noise import ActionNoise

__all__ = ["HeldActionNoise", "pink_action_noise"]


class HeldActionNoise(ActionNoise):
    """Each draw of ``noise`` repeated for ``hold`` consecutive calls (one draw per action chunk); :meth:`reset` (at an
    episode's end) makes the next call draw again.

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
    """``pink-noise-rl``'s ``PinkActionNoise`` with a generator seeded by ``seed`` (the package's is unseeded).

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
