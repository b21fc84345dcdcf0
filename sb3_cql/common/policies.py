"""CQL's policies are SAC's (actor, twin critics), with an optional observation normaliser as features extractor."""

from __future__ import annotations

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.sac.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, SACPolicy

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "NormalizedFlatten", "SACPolicy"]


class NormalizedFlatten(BaseFeaturesExtractor):
    """Flatten a Box observation and z-score it with fixed statistics (the dataset's, set by CQL).

    The statistics are buffers of the module, so they are saved and loaded with the policy's ``state_dict`` and
    applied in ``predict`` as in training. Until they are set they are the identity (mean 0, std 1).

    :param observation_space: a Box observation space.
    """

    def __init__(self, observation_space: spaces.Box) -> None:
        size = int(np.prod(observation_space.shape))
        super().__init__(observation_space, features_dim=size)
        self.register_buffer("mean", th.zeros(size))
        self.register_buffer("std", th.ones(size))

    def set_statistics(self, mean: np.ndarray, std: np.ndarray) -> None:
        """Use ``mean`` and ``std`` (flattened observation shape) from now on; a std below 1e-6 counts as 1e-6."""
        self.mean.copy_(th.as_tensor(mean, dtype=th.float32).reshape(-1))
        self.std.copy_(th.as_tensor(np.maximum(std, 1e-6), dtype=th.float32).reshape(-1))

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return (observations.flatten(start_dim=1) - self.mean) / self.std
