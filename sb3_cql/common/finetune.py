"""Online fine-tuning of an offline model: SB3's SAC loop on a :class:`~sb3_cql.common.MixedReplayBuffer`."""

from __future__ import annotations

import io
import os
from typing import Any

import numpy as np
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.noise import ActionNoise

from sb3_cql.common.buffers import MixedReplayBuffer, ReturnToGoReplayBuffer
from sb3_cql.common.settings import check_finite_observation


class OnlineFineTuning(SAC):
    """What :class:`~sb3_cql.common.OfflineSAC` does with ``online_fraction`` set: :meth:`learn_online` is SAC's
    ``learn`` on a buffer whose batches draw ``online_fraction`` of their samples from the online transitions, the
    rest from the model's offline data (:meth:`~sb3_cql.common.OfflineSAC.load_offline_data`)."""

    online_fraction: float | None
    online_buffer_size: int
    deterministic_rollouts: bool
    action_chunk: int

    def learn_online(self, total_timesteps: int, callback: Any, log_interval: int | None, tb_log_name: str,
                     reset_num_timesteps: bool, progress_bar: bool) -> Any:  # fmt: skip
        """SAC's ``learn`` for ``total_timesteps`` env steps on the mixed buffer (the arguments are SB3's)."""
        self._prepare_online_buffer(reset_num_timesteps)
        # SB3's learn starts (or continues) with a new chunk, and resets the action noise with it.
        self._rollout_chunks, self._rollout_episode_starts = None, np.ones(self.n_envs, dtype=bool)
        log_interval = 4 if log_interval is None else log_interval
        return SAC.learn(self, total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """SAC's exploration, or with ``deterministic_rollouts`` TD3's (the deterministic action plus ``action_noise``,
        clipped); action chunks run open loop through the policy's ``state``. The first ``learning_starts`` steps act
        as the rest do (WSRL's warm-up), not at random."""
        chunked = self.action_chunk > 1
        if not self.deterministic_rollouts and not chunked:
            return super()._sample_action(0, action_noise, n_envs)
        assert self._last_obs is not None
        if chunked:
            action, self._rollout_chunks = self.policy.predict(
                self._last_obs, self._rollout_chunks, self._rollout_episode_starts, deterministic=self.deterministic_rollouts
            )
            self._rollout_episode_starts = np.zeros(n_envs, dtype=bool)
        else:
            action, _ = self.predict(self._last_obs, deterministic=True)
        scaled_action = self.policy.scale_action(action)
        if action_noise is not None:
            scaled_action = np.clip(scaled_action + action_noise(), -1, 1)
        return self.policy.unscale_action(scaled_action), scaled_action

    def _store_transition(self, replay_buffer: ReplayBuffer, buffer_action: np.ndarray, new_obs: Any,
                          reward: np.ndarray, dones: np.ndarray, infos: list[dict[str, Any]]) -> None:  # fmt: skip
        check_finite_observation(new_obs, "the env's observation")  # at the step it arrives, before any training on it
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        if self.action_chunk > 1:  # an episode that ended starts the next with a new chunk
            self._rollout_episode_starts = self._rollout_episode_starts | np.asarray(dones, dtype=bool)

    def _prepare_online_buffer(self, reset_num_timesteps: bool) -> None:
        """Make the replay buffer a :class:`MixedReplayBuffer` of the offline data and an online part."""
        mixed = self.replay_buffer if isinstance(self.replay_buffer, MixedReplayBuffer) else None
        if mixed is None:
            offline = self.load_offline_data()
            mixed = MixedReplayBuffer(offline, self._empty_buffer_like(offline), self.online_fraction)
        elif mixed.offline is None:  # a loaded buffer of online transitions: the offline data come from the dataset
            self.replay_buffer = None
            try:
                offline = self.load_offline_data()
            finally:
                self.replay_buffer = mixed  # kept, also when the data cannot be loaded
            mixed.set_offline(offline)
        mixed.online_fraction = self.online_fraction  # a fraction given to load() applies to a loaded buffer too
        self.replay_buffer = mixed
        if reset_num_timesteps or self._last_obs is None:  # SB3's learn resets the env: a new episode starts
            mixed.start_new_episodes()

    def _empty_buffer_like(self, buffer: ReplayBuffer) -> ReplayBuffer:
        """An empty buffer of ``online_buffer_size`` of ``buffer``'s class and settings, for this model's env."""
        kwargs: dict[str, Any] = {}
        if isinstance(buffer, NStepReplayBuffer):
            kwargs = {"gamma": buffer.gamma, "n_steps": buffer.n_steps}
        if isinstance(buffer, ReturnToGoReplayBuffer):
            kwargs.update(reward_scale=buffer.reward_scale, reward_bias=buffer.reward_bias)
        return type(buffer)(
            self.online_buffer_size,
            self.observation_space,
            self.action_space,
            device=self.device,
            n_envs=self.n_envs,
            handle_timeout_termination=True,
            **kwargs,
        )

    def load_replay_buffer(self, path: str | os.PathLike | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """SB3's; the offline data this model holds stay under a loaded buffer of online transitions (else
        :meth:`learn` reloads them from the dataset id)."""
        offline = self.replay_buffer.offline if isinstance(self.replay_buffer, MixedReplayBuffer) else self.replay_buffer
        super().load_replay_buffer(path, truncate_last_traj)
        loaded = self.replay_buffer
        keeps = offline is not None and offline.size() >= self.batch_size
        if isinstance(loaded, MixedReplayBuffer) and loaded.offline is None and keeps and type(offline) is type(loaded.online):
            loaded.set_offline(offline)
