"""Exploration noise kept for the studies, a subclass of :class:`sb3_cql.zoo.callbacks.ExplorationNoise`.

- :class:`ArmExplorationNoise`: the shipped pink noise on the seven arm joints' actions only, the fingers' actions
  left as the policy gives them (whether exploring in the fingers is what makes fine-tuned policies stop closing the
  hand, ``research/studies/layernorm-critics``; ``research/hyperparams/iql_finetune_arm_noise.yml``).

Not part of the package (nothing in ``sb3_cql`` imports it). A zoo config names it from the repository's root::

    callback:
      - research.exploration.ArmExplorationNoise:
          pink_std: 0.1
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.noise import ActionNoise

from envs.robot import ARM_JOINTS
from sb3_cql.zoo.callbacks import ExplorationNoise


class MaskedActionNoise(ActionNoise):
    """``noise`` on the action dimensions where ``mask`` is true, 0 elsewhere."""

    def __init__(self, noise: ActionNoise, mask: np.ndarray) -> None:
        super().__init__()
        self.noise, self.mask = noise, np.asarray(mask, dtype=bool)

    def __call__(self) -> np.ndarray:
        return np.where(self.mask, self.noise(), 0.0)

    def reset(self, **kwargs) -> None:
        self.noise.reset(**kwargs)


class ArmExplorationNoise(ExplorationNoise):
    """:class:`ExplorationNoise` on the arm joints' actions (the first ``len(ARM_JOINTS)``) only."""

    def _init_callback(self) -> None:
        super()._init_callback()
        mask = np.arange(self.model.action_space.shape[0]) < len(ARM_JOINTS)
        self.model.action_noise = MaskedActionNoise(self.model.action_noise, mask)
        print(f"Exploration noise on the action dimensions {np.flatnonzero(mask).tolist()} only")
