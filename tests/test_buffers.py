"""Returns-to-go and the replay buffer that holds them (calibrated CQL's bound), on hand-made episodes."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql.common import ReturnToGoReplayBuffer, returns_to_go

OBSERVATIONS = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
ACTIONS = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)


def test_returns_to_go_of_a_terminated_episode_stop_at_its_end():
    np.testing.assert_allclose(returns_to_go([-2.0, -2.0, 2.0], truncated=False, gamma=0.5), [-2.5, -1.0, 2.0])


def test_a_cut_episode_of_equal_rewards_earns_them_forever():
    # The Cal-QL paper's sparse-reward rule: a failed episode would not have succeeded later.
    np.testing.assert_allclose(returns_to_go([-2.0] * 4, truncated=True, gamma=0.99), [-200.0] * 4)
    # Terminated, the same rewards stop at the end.
    np.testing.assert_allclose(returns_to_go([-2.0, -2.0], truncated=False, gamma=0.99), [-3.98, -2.0])


def test_a_cut_episode_of_other_rewards_counts_them_up_to_the_cut():
    np.testing.assert_allclose(returns_to_go([0.0, 1.0, 0.0], truncated=True, gamma=0.5), [0.5, 1.0, 0.0])


def add(buffer: ReplayBuffer, reward: float, done: bool = False, truncated: bool = False, value: float = 0.0) -> None:
    """One transition whose observation holds ``value`` (to find it again)."""
    observation = np.full(2, value, dtype=np.float32)
    buffer.add(observation, observation, np.zeros(1), np.array([reward]), np.array([done or truncated]),
               [{"TimeLimit.truncated": truncated}])  # fmt: skip


def test_online_episodes_get_their_returns_to_go_when_they_end():
    buffer = ReturnToGoReplayBuffer(4, OBSERVATIONS, ACTIONS, gamma=0.5, reward_scale=4.0, reward_bias=-2.0)
    add(buffer, 0.0)
    add(buffer, 0.0)
    assert np.all(buffer.returns_to_go[:2, 0] == -np.inf)  # the episode has not ended
    add(buffer, 1.0, done=True)  # rewards as the critics see them: -2, -2, 2
    np.testing.assert_allclose(buffer.returns_to_go[:3, 0], [-2.5, -1.0, 2.0])
    # A failed episode cut by the time limit, wrapping around the end of the buffer (rows 3, 0).
    add(buffer, 0.0)
    add(buffer, 0.0, truncated=True)
    np.testing.assert_allclose(buffer.returns_to_go[[3, 0], 0], [-4.0, -4.0])
    np.testing.assert_allclose(buffer.returns_to_go[1:3, 0], [-1.0, 2.0])  # what is left of the first episode


def test_a_filled_buffer_is_upgraded_in_place_and_continues_online():
    plain = ReplayBuffer(10, OBSERVATIONS, ACTIONS)
    for reward, done in [(0.0, False), (1.0, True), (0.0, False), (0.0, False)]:  # an ended episode, one under way
        add(plain, reward, done=done)
    plain.timeouts[:] = False
    buffer = ReturnToGoReplayBuffer.from_replay_buffer(plain, gamma=0.9, reward_scale=1.0, reward_bias=-1.0)
    assert np.shares_memory(buffer.observations, plain.observations) and buffer.size() == 4
    np.testing.assert_allclose(buffer.returns_to_go[:2, 0], [-1.0, 0.0])
    assert np.all(buffer.returns_to_go[2:4, 0] == -np.inf)
    add(buffer, 0.0, truncated=True)  # the episode under way ends: all its rewards are -1
    np.testing.assert_allclose(buffer.returns_to_go[2:5, 0], [-10.0] * 3)


def test_samples_carry_the_returns_to_go_of_their_states():
    buffer = ReturnToGoReplayBuffer(8, OBSERVATIONS, ACTIONS, gamma=0.5)
    for step, reward in enumerate([0.0, 0.0, 1.0]):
        add(buffer, reward, done=step == 2, value=step / 10)
    samples = buffer.sample(32)
    expected = {0.0: 0.25, 0.1: 0.5, 0.2: 1.0}
    for observation, value in zip(samples.observations[:, 0].tolist(), samples.returns_to_go[:, 0].tolist()):
        assert value == pytest.approx(expected[round(observation, 1)])
    assert isinstance(samples.returns_to_go, th.Tensor) and samples.dones.shape == (32, 1)
