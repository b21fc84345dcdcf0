"""``load_offline_data``: a model's offline data in its replay buffer, as ``learn`` has them before training."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql import BC, CQL
from sb3_cql.common import SettingError

TINY = {"net_arch": [32]}


def pendulum_buffer(n_transitions: int) -> ReplayBuffer:
    """Random Pendulum transitions."""
    env = gym.make("Pendulum-v1")
    buffer = ReplayBuffer(n_transitions, env.observation_space, env.action_space)
    rng = np.random.default_rng(0)
    for _ in range(n_transitions):
        observation = env.observation_space.sample()
        action = rng.uniform(-1, 1, size=1).astype(np.float32)
        buffer.add(observation, observation, action, np.array([0.0]), np.array([False]), [{}])
    return buffer


def test_a_buffer_of_a_batch_or_more_is_kept_as_it_is():
    buffer = pendulum_buffer(200)
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=64, policy_kwargs=TINY)
    assert model.load_offline_data() is model.replay_buffer and model.replay_buffer.size() == 200


def test_a_loaded_model_without_a_dataset_id_is_refused(tmp_path):
    model = BC("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(200), batch_size=64, policy_kwargs=TINY)
    model.save(tmp_path / "bc")
    loaded = BC.load(tmp_path / "bc", env=gym.make("Pendulum-v1"))
    with pytest.raises(SettingError, match="the buffer has 0 .*none here"):
        loaded.load_offline_data()


def test_a_loaded_model_reloads_its_data_from_its_dataset_id(tmp_path, monkeypatch):
    from sb3_cql.data import CollectionSpec, collect_dataset

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = collect_dataset(CollectionSpec(n_episodes=2), progress_bar=False)
    model = CQL("MlpPolicy", "Panda-v0", dataset="sb3cql/Panda-v0/pid-v0", batch_size=32, policy_kwargs=TINY)
    model.save(tmp_path / "model")
    loaded = CQL.load(tmp_path / "model", env=gym.make("Panda-v0"))
    assert loaded.replay_buffer.size() < loaded.batch_size
    buffer = loaded.load_offline_data()
    assert buffer is loaded.replay_buffer and buffer.size() == dataset.total_steps
    assert loaded.load_offline_data() is buffer  # kept, not reloaded
