"""What the offline algorithms share: SAC's networks trained from a dataset instead of an env, and fine-tuned online."""

from sb3_cql.common.buffers import (
    ActionChunkReplayBuffer,
    MixedReplayBuffer,
    ReturnToGoReplayBuffer,
    ReturnToGoSamples,
    returns_to_go,
    with_n_step_returns,
)
from sb3_cql.common.noise import HeldActionNoise, pink_action_noise
from sb3_cql.common.offline import OfflineSAC, SettingError, TrainingDivergedError, behaviour_cloning_loss

__all__ = [
    "ActionChunkReplayBuffer",
    "HeldActionNoise",
    "MixedReplayBuffer",
    "OfflineSAC",
    "ReturnToGoReplayBuffer",
    "ReturnToGoSamples",
    "SettingError",
    "TrainingDivergedError",
    "behaviour_cloning_loss",
    "pink_action_noise",
    "returns_to_go",
    "with_n_step_returns",
]
