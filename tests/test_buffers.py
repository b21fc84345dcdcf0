"""Returns-to-go and the replay buffer that holds them (calibrated CQL's bound), and the buffer of online fine-tuning
that keeps the offline data beside the online transitions, on hand-made episodes."""

import copy
import pickle

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql.common import MixedReplayBuffer, ReturnToGoReplayBuffer, returns_to_go

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
    for observation, value in zip(samples.observations[:, 0].tolist(), samples.returns_to_go[:, 0].tolist(), strict=True):
        assert value == pytest.approx(expected[round(observation, 1)])
    assert isinstance(samples.returns_to_go, th.Tensor) and samples.dones.shape == (32, 1)


def mixed_buffer(online_fraction: float, capacity: int = 100) -> MixedReplayBuffer:
    """Offline transitions marked -1 (an ended episode of 10), an empty online part of ``capacity``."""
    offline = ReturnToGoReplayBuffer(10, OBSERVATIONS, ACTIONS, gamma=0.5)
    for step in range(10):
        add(offline, 1.0 if step == 9 else 0.0, done=step == 9, value=-1.0)
    online = ReturnToGoReplayBuffer(capacity, OBSERVATIONS, ACTIONS, gamma=0.5)
    return MixedReplayBuffer(offline, online, online_fraction)


def test_batches_draw_the_set_fraction_from_the_online_transitions():
    buffer = mixed_buffer(online_fraction=0.25)
    assert buffer.sample(8).observations[:, 0].tolist() == [-1.0] * 8  # nothing online yet: all offline
    add(buffer, 0.0, value=1.0)  # added transitions go online
    assert (buffer.online.size(), buffer.offline.size(), buffer.size()) == (1, 10, 11)
    samples = buffer.sample(8)
    assert sorted(samples.observations[:, 0].tolist()) == [-1.0] * 6 + [1.0] * 2
    assert np.all(samples.returns_to_go[-2:].numpy() == -np.inf)  # the online episode has not ended
    add(buffer, 1.0, done=True, value=1.0)  # the online episode ends: returns-to-go 0.5, 1.0
    assert set(buffer.sample(8).returns_to_go[-2:].flatten().tolist()) <= {0.5, 1.0}
    assert sorted(mixed_buffer(online_fraction=1.0).sample(4).observations[:, 0].tolist()) == [-1.0] * 4
    with pytest.raises(ValueError, match="online_fraction"):
        mixed_buffer(online_fraction=1.5)


def test_a_pickled_mixed_buffer_keeps_the_online_transitions_up_to_its_size():
    buffer = mixed_buffer(online_fraction=0.5, capacity=100_000)
    add(buffer, 0.0, value=1.0)
    add(buffer, 0.0, value=2.0)
    copy = pickle.loads(pickle.dumps(buffer))
    assert len(pickle.dumps(buffer)) < 100_000  # the filled rows only, not the capacity, and no offline data
    assert copy.offline is None and copy.online.size() == 2 and copy.online.buffer_size == 100_000
    np.testing.assert_array_equal(copy.online.observations[:3, 0, 0], [1.0, 2.0, 0.0])
    assert np.all(copy.online.returns_to_go == -np.inf)
    with pytest.raises(ValueError, match="no offline data"):
        copy.sample(4)
    copy.set_offline(buffer.offline)
    copy.start_new_episodes()  # the env was reset (training resumed): the unfinished episode stays unbounded
    add(copy, 1.0, done=True, value=3.0)
    np.testing.assert_allclose(copy.online.returns_to_go[:3, 0], [-np.inf, -np.inf, 1.0])
    with pytest.raises(ValueError, match="one class"):
        copy.set_offline(ReplayBuffer(10, OBSERVATIONS, ACTIONS))


def test_a_mixed_buffer_is_a_replay_buffer_of_its_online_part():
    buffer = mixed_buffer(online_fraction=0.5, capacity=4)
    for step in range(6):  # wraps around the online capacity
        add(buffer, 0.0, value=float(step))
    assert isinstance(buffer, ReplayBuffer)
    assert (buffer.pos, buffer.full, buffer.buffer_size) == (2, True, 4)
    assert buffer.observations is buffer.online.observations and buffer.actions.shape == (4, 1, 1)
    np.testing.assert_array_equal(buffer.observations[:, 0, 0], [4.0, 5.0, 2.0, 3.0])
    assert buffer.size() == 4 + 10 and buffer.obs_shape == (2,) and buffer.action_dim == 1


def test_a_deep_copy_of_a_mixed_buffer_keeps_both_parts():
    buffer = mixed_buffer(online_fraction=0.5)
    add(buffer, 0.0, value=1.0)
    duplicate = copy.deepcopy(buffer)
    assert duplicate.size() == buffer.size() == 11 and duplicate.offline is not buffer.offline
    np.testing.assert_array_equal(duplicate.offline.observations, buffer.offline.observations)
    add(duplicate, 0.0, value=2.0)
    assert (duplicate.online.size(), buffer.online.size()) == (2, 1)
