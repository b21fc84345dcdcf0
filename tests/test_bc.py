"""Behaviour cloning: imitation of a dataset's actions through SB3's API, save/load, and the zoo's name for it."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import configure

from sb3_cql import BC, CQL
from sb3_cql.common import SettingError

TINY = {"net_arch": [64, 64]}


def expert_pendulum_buffer(n_transitions: int = 2000, seed: int = 0) -> ReplayBuffer:
    """Pendulum transitions from random states, labelled with a fixed nonlinear controller's action."""
    env = gym.make("Pendulum-v1")
    buffer = ReplayBuffer(n_transitions, env.observation_space, env.action_space)
    rng = np.random.default_rng(seed)
    for _ in range(n_transitions):
        observation = env.observation_space.sample() * rng.uniform(0.2, 1.0)
        buffer.add(observation, observation, expert_action(observation[None])[0], np.array([0.0]), np.array([False]),
                   [{"TimeLimit.truncated": False}])  # fmt: skip
    return buffer


def expert_action(observations: np.ndarray) -> np.ndarray:
    """The controller, in SB3's [-1, 1] action units."""
    return np.tanh(-1.5 * observations[:, 1:2] - 0.3 * observations[:, 2:3]).astype(np.float32)


def test_bc_imitates_the_datasets_actions(tmp_path):
    buffer = expert_pendulum_buffer()
    model = BC("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=128, policy_kwargs=TINY, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    observations = buffer.observations[:500, 0]
    targets = expert_action(observations) * 2.0  # Pendulum's actions are in [-2, 2]
    error_before = np.abs(model.predict(observations, deterministic=True)[0] - targets).mean()
    model.learn(600, log_interval=100)
    error_after = np.abs(model.predict(observations, deterministic=True)[0] - targets).mean()
    assert error_after < 0.1 < error_before
    critic_before = BC("MlpPolicy", "Pendulum-v1", dataset=buffer, policy_kwargs=TINY, seed=0).critic.state_dict()
    for name, tensor in model.critic.state_dict().items():  # BC leaves the critics alone
        np.testing.assert_array_equal(tensor.numpy(), critic_before[name].numpy())
    assert "train/actor_loss" in (tmp_path / "progress.csv").read_text()


def test_bc_save_and_load_predict_the_same(tmp_path):
    env = gym.make("Pendulum-v1")
    model = BC("MlpPolicy", env, dataset=expert_pendulum_buffer(300), batch_size=64, policy_kwargs=TINY, seed=0)
    model.learn(20)
    model.save(tmp_path / "bc")
    loaded = BC.load(tmp_path / "bc", env=env)
    assert loaded.replay_buffer.buffer_size == 1
    observations = np.stack([env.observation_space.sample() for _ in range(16)])
    np.testing.assert_array_equal(loaded.predict(observations, deterministic=True)[0],
                                  model.predict(observations, deterministic=True)[0])  # fmt: skip


@pytest.mark.parametrize("algo", [BC, CQL])
def test_a_loaded_model_trains_on_its_dataset_again(tmp_path, monkeypatch, algo):
    from sb3_cql.data import CollectionSpec, collect_dataset

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = collect_dataset(CollectionSpec(n_episodes=2), progress_bar=False)
    model = algo("MlpPolicy", "Panda-v0", dataset="sb3cql/Panda-v0/pid-v0", batch_size=32, policy_kwargs=TINY)
    model.learn(5)
    model.save(tmp_path / "model")
    loaded = algo.load(tmp_path / "model", env=gym.make("Panda-v0"))
    assert loaded.replay_buffer.buffer_size == 1 and loaded.dataset == "sb3cql/Panda-v0/pid-v0"
    loaded.learn(5, reset_num_timesteps=False)  # as the zoo's --trained-agent continues a run
    assert loaded.replay_buffer.size() == dataset.total_steps and loaded.num_timesteps == 10


@pytest.mark.parametrize("batch_size", [0, -5])
def test_a_batch_size_below_one_is_refused(batch_size):
    with pytest.raises(SettingError, match=f"^batch_size must be an integer >= 1, got {batch_size}$"):
        BC("MlpPolicy", "Pendulum-v1", dataset=expert_pendulum_buffer(64), batch_size=batch_size, policy_kwargs=TINY)
