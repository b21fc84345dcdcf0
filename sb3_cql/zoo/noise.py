"""Two noise keys of ours beside the zoo's ``normal`` and ``ornstein-uhlenbeck``: ``noise_type: pink`` (with
``noise_std``; ``pink-noise-rl``'s, seeded by the run's seed) and ``noise_hold: N`` (each draw of the noise held for N
steps). They leave the hyperparameters before the zoo reads its noise keys, and become the model's ``action_noise``
once it exists."""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from sb3_cql.common.noise import HeldActionNoise, pink_action_noise
from sb3_cql.zoo.errors import PROG

#: Steps of a pink-noise sequence on an env without a time limit.
PINK_SEQ_LEN = 1000


def read_noise_settings(manager: Any, hyperparams: dict[str, Any]) -> None:
    """Take our noise keys out of ``hyperparams`` into ``manager._sb3_cql_noise``, ``(type, std, hold)``."""
    hold = hyperparams.pop("noise_hold", 1)
    if not isinstance(hold, int) or hold < 1:
        raise SystemExit(f"{PROG}: error: noise_hold must be an integer >= 1, got {hold!r}")
    noise_type, noise_std = None, None
    if str(hyperparams.get("noise_type", "")).strip() == "pink":
        noise_type, noise_std = "pink", hyperparams.pop("noise_std", None)
        del hyperparams["noise_type"]
        if not isinstance(noise_std, (int, float)) or noise_std < 0:
            raise SystemExit(f"{PROG}: error: noise_type pink needs noise_std >= 0, got {noise_std!r}")
    if hold > 1 and noise_type is None and hyperparams.get("noise_type") is None:
        raise SystemExit(f"{PROG}: error: noise_hold holds the draws of a noise_type: give one")
    manager._sb3_cql_noise = (noise_type, noise_std, hold)


def apply_action_noise(manager: Any, model: Any) -> None:
    """The noise :func:`read_noise_settings` read as ``model.action_noise``."""
    noise_type, noise_std, hold = getattr(manager, "_sb3_cql_noise", (None, None, 1))
    if noise_type == "pink":
        seq_len = gym.spec(manager.env_name.gym_id).max_episode_steps or PINK_SEQ_LEN
        model.action_noise = pink_action_noise(float(noise_std), model.action_space.shape[0], seq_len, seed=manager.seed)
        print(f"Applying pink noise with std {noise_std} (sequences of {seq_len} steps)")
    if hold > 1 and model.action_noise is not None:
        model.action_noise = HeldActionNoise(model.action_noise, hold)
        print(f"Each draw of the noise is held for {hold} steps")
