"""What the offline algorithms share: SAC's networks trained from a dataset instead of an env, and fine-tuned online.

Each name loads its module (and with it torch and SB3) on first use, so that :mod:`sb3_cql.common.atomic`, which the
datasets and the protocol's records write through, imports neither.
"""

import importlib

#: Where each name of the package lives.
_MODULES = {name: module for module, names in {
    "buffers": ("ActionChunkReplayBuffer", "MixedReplayBuffer", "ReturnToGoReplayBuffer", "ReturnToGoSamples", "returns_to_go",
                "with_n_step_returns"),
    "noise": ("HeldActionNoise", "pink_action_noise"),
    "offline": ("OfflineSAC", "behaviour_cloning_loss", "frozen"),
    "finetune": ("OnlineFineTuning",),
    "settings": ("KeywordError", "SettingError", "TrainingDivergedError"),
}.items() for name in names}  # fmt: skip


def __getattr__(name: str):
    if name in _MODULES:
        return getattr(importlib.import_module(f"sb3_cql.common.{_MODULES[name]}"), name)
    raise AttributeError(f"module 'sb3_cql.common' has no attribute {name!r}")


__all__ = sorted(_MODULES)
