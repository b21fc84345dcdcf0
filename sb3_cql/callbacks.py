"""SB3 callbacks of the package."""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback

from sb3_cql.data import fill_replay_buffer


class PrefillReplayBuffer(BaseCallback):
    """Append a dataset's transitions to an off-policy model's replay buffer before its first step: online SAC
    (or TD3, ...) that starts from the behaviour data, the thesis's SAC baseline. In an RL-Zoo3 config::

        callback:
          - sb3_cql.callbacks.PrefillReplayBuffer:
              dataset: sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0

    The buffer grows to the data's size if ``buffer_size`` cannot hold them; it is then full, and online
    transitions replace the oldest data first, as in any full SB3 buffer.

    :param dataset: a Minari id (a missing standard id is collected first, :func:`sb3_cql.data.ensure_dataset`).
    :param verbose: 1 prints how many transitions were added.
    """

    def __init__(self, dataset: str, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.dataset = dataset

    def _on_training_start(self) -> None:
        buffer = getattr(self.model, "replay_buffer", None)
        if buffer is None:
            raise TypeError(f"PrefillReplayBuffer needs an off-policy model, got {type(self.model).__name__}")
        before = buffer.size()
        self.model.replay_buffer = fill_replay_buffer(self.dataset, self.model.observation_space, self.model.action_space,
                                                      buffer)  # fmt: skip
        if self.verbose:
            print(f"Replay buffer: {self.model.replay_buffer.size() - before} transitions from {self.dataset}")

    def _on_step(self) -> bool:
        return True
