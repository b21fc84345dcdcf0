"""A replay buffer that also holds each transition's discounted return-to-go, for calibrated CQL (Cal-QL)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize


class ReturnToGoSamples(NamedTuple):
    """SB3's ``ReplayBufferSamples`` and the return-to-go of each sampled state (``-inf`` where its episode has not
    ended yet)."""

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    returns_to_go: th.Tensor


def returns_to_go(rewards: np.ndarray, truncated: bool, gamma: float) -> np.ndarray:
    """Discounted returns-to-go ``G_t = r_t + gamma * G_{t+1}`` of one whole episode, in float64.

    A terminated episode (``truncated`` False) has ``G = 0`` after its last step. An episode cut by a time limit whose
    rewards are all equal, such as a sparse-reward episode that never reached the goal, is taken to go on earning that
    reward forever: ``G_t = r / (1 - gamma)`` at every step, as the Cal-QL paper does for failed episodes of sparse-
    reward tasks (it assumes the agent would not succeed later). Any other cut episode counts its rewards up to the cut.

    :param rewards: the episode's rewards, as the critics see them (after any scaling).
    :param truncated: whether the episode ended by a time limit rather than by termination.
    :param gamma: discount factor.
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    if truncated and len(rewards) > 0 and np.all(rewards == rewards[0]):
        return np.full(len(rewards), rewards[0] / (1.0 - gamma))
    result = np.empty(len(rewards))
    following = 0.0
    for step in range(len(rewards) - 1, -1, -1):
        following = rewards[step] + gamma * following
        result[step] = following
    return result


class ReturnToGoReplayBuffer(ReplayBuffer):
    """SB3's ``ReplayBuffer`` with the discounted return-to-go of every stored state, under the critics' reward
    transform ``reward_scale * reward + reward_bias`` (:func:`returns_to_go`). Samples are
    :class:`ReturnToGoSamples`.

    Transitions added one step at a time (online interaction) get their returns-to-go when their episode ends
    (``done``, a termination or, with ``TimeLimit.truncated`` in its info, a truncation); until then they read as
    ``-inf``. A buffer filled in bulk (:meth:`from_replay_buffer`, or by writing its arrays) gets them from
    :meth:`compute_returns_to_go`.

    :param gamma: discount factor.
    :param reward_scale: the critics' reward scale.
    :param reward_bias: the critics' reward bias.
    :param args: ``ReplayBuffer``'s (``buffer_size``, ``observation_space``, ``action_space``, ...).
    :param kwargs: ``ReplayBuffer``'s.
    """

    def __init__(
        self, *args: Any, gamma: float = 0.99, reward_scale: float = 1.0, reward_bias: float = 0.0, **kwargs: Any
    ) -> None:
        super().__init__(*args, **kwargs)
        if self.optimize_memory_usage:
            raise ValueError("ReturnToGoReplayBuffer does not support optimize_memory_usage")
        self.gamma, self.reward_scale, self.reward_bias = gamma, reward_scale, reward_bias
        self.returns_to_go = np.full((self.buffer_size, self.n_envs), -np.inf, dtype=np.float32)
        self.episode_starts = np.zeros(self.n_envs, dtype=np.int64)  # where each env's running episode began

    @classmethod
    def from_replay_buffer(
        cls, buffer: ReplayBuffer, gamma: float, reward_scale: float = 1.0, reward_bias: float = 0.0
    ) -> ReturnToGoReplayBuffer:
        """A buffer holding ``buffer``'s transitions (its arrays, shared, not copied) and their returns-to-go.
        Episodes are delimited by ``dones`` and ``timeouts``; a last episode without an end gets ``-inf``."""
        if buffer.optimize_memory_usage:
            raise ValueError("ReturnToGoReplayBuffer does not support optimize_memory_usage")
        upgraded = cls.__new__(cls)
        upgraded.__dict__.update(buffer.__dict__)
        upgraded.gamma, upgraded.reward_scale, upgraded.reward_bias = gamma, reward_scale, reward_bias
        upgraded.returns_to_go = np.full((buffer.buffer_size, buffer.n_envs), -np.inf, dtype=np.float32)
        upgraded.episode_starts = np.zeros(buffer.n_envs, dtype=np.int64)
        upgraded.compute_returns_to_go()
        return upgraded

    def compute_returns_to_go(self) -> None:
        """Returns-to-go of every ended episode in the buffer, read in storage order from the oldest transition
        (``-inf`` for a trailing episode without an end; it continues where the next :meth:`add` writes)."""
        size = self.size()
        order = (np.arange(size) + (self.pos if self.full else 0)) % self.buffer_size
        for env in range(self.n_envs):
            start = 0
            ends = self.dones[order, env].astype(bool) | self.timeouts[order, env].astype(bool)
            for end in np.flatnonzero(ends):
                self._set_episode(order[start : end + 1], env)
                start = end + 1
            self.returns_to_go[order[start:], env] = -np.inf
            self.episode_starts[env] = order[start] if start < size else self.pos

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        row = self.pos
        super().add(obs, next_obs, action, reward, done, infos)
        self.returns_to_go[row] = -np.inf
        for env in np.flatnonzero(np.asarray(done).reshape(self.n_envs)):
            length = (row - self.episode_starts[env]) % self.buffer_size + 1
            rows = (self.episode_starts[env] + np.arange(length)) % self.buffer_size
            self._set_episode(rows, int(env))
            self.episode_starts[env] = self.pos

    def _set_episode(self, rows: np.ndarray, env: int) -> None:
        rewards = self.reward_scale * self.rewards[rows, env].astype(np.float64) + self.reward_bias
        truncated = bool(self.timeouts[rows[-1], env])
        self.returns_to_go[rows, env] = returns_to_go(rewards, truncated, self.gamma)

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> ReturnToGoSamples:
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        data = (
            self._normalize_obs(self.observations[batch_inds, env_indices, :], env),
            self.actions[batch_inds, env_indices, :],
            self._normalize_obs(self.next_observations[batch_inds, env_indices, :], env),
            # As SB3's: a timeout is not a termination for the backup.
            (self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])).reshape(-1, 1),
            self._normalize_reward(self.rewards[batch_inds, env_indices].reshape(-1, 1), env),
            self.returns_to_go[batch_inds, env_indices].reshape(-1, 1),
        )
        return ReturnToGoSamples(*tuple(map(self.to_torch, data)))
