"""Random rollouts of an env in a replay buffer of its own spaces: the datasets of the algorithms' unit tests; and the
arguments that collect the command-line tests' dataset."""

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer

#: ``python -m sb3_cql.data`` arguments that collect 4 episodes as ``sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0``, the
#: dataset our zoo configs name: the command-line tests' stand-in for the full one.
TINY_PANDA_COLLECT = ("collect", "--policy", "noisy-regrasp", "--action-mode", "delta", "--episodes", "4",
                      "--dataset-id", "sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0")  # fmt: skip


def random_rollouts(env: gym.Env, n_transitions: int, seed: int = 0) -> ReplayBuffer:
    """``n_transitions`` random transitions of ``env`` in a buffer of its own spaces (as a user collects them:
    channel-last images as the env gives them, Dict observations in a ``DictReplayBuffer``), actions scaled to
    [-1, 1] as SB3 stores them, ``TimeLimit.truncated`` kept."""
    buffer_class = DictReplayBuffer if isinstance(env.observation_space, spaces.Dict) else ReplayBuffer
    buffer = buffer_class(n_transitions, env.observation_space, env.action_space)
    env.action_space.seed(seed)
    observation, _ = env.reset(seed=seed)
    low, high = env.action_space.low, env.action_space.high
    for _ in range(n_transitions):
        action = env.action_space.sample()
        next_observation, reward, terminated, truncated, _ = env.step(action)
        buffer.add(observation, next_observation, 2 * (action - low) / (high - low) - 1, np.array([reward]),
                   np.array([terminated or truncated]), [{"TimeLimit.truncated": truncated}])  # fmt: skip
        observation = next_observation if not (terminated or truncated) else env.reset()[0]
    return buffer


def spaces_env(observation_space: spaces.Space, action_space: spaces.Space) -> gym.Env:
    """An env of these spaces (SB3 needs one; offline training never steps it): random observations, 0 reward."""

    class SpacesEnv(gym.Env):
        def __init__(self) -> None:
            self.observation_space, self.action_space = observation_space, action_space

        def reset(self, *, seed=None, options=None):
            return self.observation_space.sample(), {}

        def step(self, action):
            return self.observation_space.sample(), 0.0, False, True, {}

    return SpacesEnv()
