"""Exploration noise the zoo's ``noise_type`` lacks (it makes ``normal`` and ``ornstein-uhlenbeck`` noise only), as a
callback a config names in its ``callback:`` list: ``- sb3_cql.zoo.callbacks.ExplorationNoise: {pink_std: 0.1}``."""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import VectorizedActionNoise

from sb3_cql.common import HeldActionNoise, SettingError, pink_action_noise

#: Steps of a pink-noise sequence on an env without a time limit.
PINK_SEQ_LEN = 1000


class ExplorationNoise(BaseCallback):
    """Set the model's action noise as training starts.

    :param pink_std: pink noise of this standard deviation per action dimension (scaled actions, [-1, 1]):
        ``pink-noise-rl``'s, a sequence an episode, seeded by the model's seed; None: the zoo's (``noise_type``).
    :param hold: steps each draw of the noise is held for (one draw a chunk of ``hold`` actions).
    """

    def __init__(self, pink_std: float | None = None, hold: int = 1) -> None:
        super().__init__()
        pink_ok = pink_std is None or (isinstance(pink_std, (int, float)) and pink_std >= 0)
        if not pink_ok or not isinstance(hold, int) or hold < 1:
            raise SettingError(f"ExplorationNoise needs pink_std >= 0 or None and hold >= 1, got {pink_std!r}, {hold!r}")
        self.pink_std, self.hold = pink_std, hold

    def _init_callback(self) -> None:
        noise, n_envs = self.model.action_noise, self.training_env.num_envs
        if self.pink_std is not None:
            seq_len = self.training_env.get_attr("spec")[0].max_episode_steps or PINK_SEQ_LEN
            noise = pink_action_noise(self.pink_std, self.model.action_space.shape[0], seq_len, seed=self.model.seed)
            noise = noise if n_envs == 1 else VectorizedActionNoise(noise, n_envs)
            print(f"Applying pink noise with std {self.pink_std} (sequences of {seq_len} steps)")
        if self.hold > 1:
            if noise is None:
                raise SettingError("ExplorationNoise's hold holds the draws of a noise: give pink_std or a noise_type")
            noise = HeldActionNoise(noise, self.hold)
        self.model.action_noise = noise

    def _on_step(self) -> bool:
        return True
