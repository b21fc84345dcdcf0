"""What the offline algorithms share: SAC's networks trained from a dataset instead of an env, and fine-tuned online.

Each name loads its module (and with it torch and SB3) on first use, so that :mod:`sb3_cql.common.atomic`, which the
datasets and the protocol's records write through, imports neither.
"""

import importlib

#: Where each name of the package lives.
_MODULES = {
    "ActionChunkReplayBuffer": "buffers",
    "MixedReplayBuffer": "buffers",
    "ReturnToGoReplayBuffer": "buffers",
    "ReturnToGoSamples": "buffers",
    "returns_to_go": "buffers",
    "with_n_step_returns": "buffers",
    "HeldActionNoise": "noise",
    "pink_action_noise": "noise",
    "OfflineSAC": "offline",
    "behaviour_cloning_loss": "offline",
    "OnlineFineTuning": "finetune",
    "KeywordError": "settings",
    "SettingError": "settings",
    "TrainingDivergedError": "settings",
}


def __getattr__(name: str):
    if name in _MODULES:
        return getattr(importlib.import_module(f"sb3_cql.common.{_MODULES[name]}"), name)
    raise AttributeError(f"module 'sb3_cql.common' has no attribute {name!r}")


__all__ = [
    "ActionChunkReplayBuffer",
    "HeldActionNoise",
    "KeywordError",
    "MixedReplayBuffer",
    "OfflineSAC",
    "OnlineFineTuning",
    "ReturnToGoReplayBuffer",
    "ReturnToGoSamples",
    "SettingError",
    "TrainingDivergedError",
    "behaviour_cloning_loss",
    "pink_action_noise",
    "returns_to_go",
    "with_n_step_returns",
]
