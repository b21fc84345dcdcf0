"""Bringing one's own data: the documentation's example from numpy arrays to trained CQL and BC models, by a Minari
dataset and by an SB3 ReplayBuffer, and the refusal of a buffer whose actions are not scaled to [-1, 1]."""

import importlib.util
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql import BC, CQL
from sb3_cql.data import DatasetError

EXAMPLE = Path(__file__).parents[1] / "examples" / "own_data.py"


def load_example():
    spec = importlib.util.spec_from_file_location("own_data", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_trains_cql_and_bc_from_arrays_by_both_routes_alike(tmp_path, monkeypatch, capsys):
    """The Minari route (the package scales the actions and reads truncations as timeouts) and the ReplayBuffer route
    (the example scales and marks them as SB3 does) load the same transitions, so the models trained from the same
    seed act alike; each model trained its steps and predicts actions in the env's space."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))  # the example sets it from --data-dir
    own_data = load_example()
    arguments = ["--episodes", "3", "--steps", "10", "--batch-size", "32", "--eval-episodes", "1", "--data-dir", str(tmp_path)]
    models = own_data.main(arguments)
    printed = capsys.readouterr().out
    assert re.search(r"data: 3 episodes, 600 transitions, mean return -?\d+\.\d", printed)
    for name in ("CQL, Minari dataset", "CQL, ReplayBuffer", "BC, Minari dataset", "BC, ReplayBuffer"):
        assert re.search(rf"{name}: mean return -?\d+\.\d over 1 episodes", printed), name
    assert isinstance(models["CQL, ReplayBuffer"], CQL) and isinstance(models["BC, ReplayBuffer"], BC)

    from_minari, from_buffer = models["CQL, Minari dataset"].replay_buffer, models["CQL, ReplayBuffer"].replay_buffer
    assert from_minari.size() == from_buffer.size() == 600
    for field in ("observations", "next_observations", "actions", "rewards", "timeouts"):
        np.testing.assert_allclose(getattr(from_minari, field)[:600], getattr(from_buffer, field)[:600], rtol=1e-6, atol=1e-6)
    assert from_buffer.timeouts[:600].sum() == 3 and np.abs(from_buffer.actions[:600]).max() <= 1.0
    np.testing.assert_array_equal(from_minari.dones[:600] * (1 - from_minari.timeouts[:600]),
                                  from_buffer.dones[:600] * (1 - from_buffer.timeouts[:600]))  # fmt: skip

    observations = from_buffer.observations[:50, 0]
    for algorithm in ("CQL", "BC"):
        first, second = models[f"{algorithm}, Minari dataset"], models[f"{algorithm}, ReplayBuffer"]
        assert first.num_timesteps == second.num_timesteps == 10
        actions, _ = first.predict(observations, deterministic=True)
        assert actions.shape == (50, 1) and np.all(np.abs(actions) <= 2.0)
        np.testing.assert_allclose(actions, second.predict(observations, deterministic=True)[0], atol=1e-5)


def raw_pendulum_buffer(scale: float) -> ReplayBuffer:
    """Pendulum-v1 transitions whose actions are the env's torques times ``scale`` (1: unscaled, in [-2, 2])."""
    env = gym.make("Pendulum-v1")
    env.action_space.seed(0)
    buffer = ReplayBuffer(100, env.observation_space, env.action_space)
    observation, _ = env.reset(seed=0)
    for _ in range(100):
        action = env.action_space.sample()
        next_observation, reward, terminated, truncated, _ = env.step(action)
        buffer.add(observation, next_observation, action * scale, np.array([reward]), np.array([terminated]),
                   [{"TimeLimit.truncated": truncated}])  # fmt: skip
        observation = next_observation
    return buffer


@pytest.mark.parametrize("algorithm", [CQL, BC])
def test_a_buffer_of_unscaled_actions_is_refused_naming_the_first_index(algorithm):
    buffer = raw_pendulum_buffer(scale=1.0)
    first = int(np.argwhere(np.abs(buffer.actions[:, 0, 0]) > 1.0)[0, 0])
    value = float(buffer.actions[first, 0, 0])
    with pytest.raises(DatasetError) as error:
        algorithm("MlpPolicy", "Pendulum-v1", dataset=buffer)
    message = str(error.value)
    assert "\n" not in message
    assert message == (f"dataset: the replay buffer's actions hold {value:g} at index {first} (action[0]), outside "
                       "[-1, 1]: store actions scaled as SB3 does (policy.scale_action)")  # fmt: skip


def test_a_buffer_of_scaled_actions_is_taken_and_a_nan_action_is_refused_before_the_range():
    buffer = raw_pendulum_buffer(scale=0.5)  # the env's [-2, 2] scaled to [-1, 1]
    buffer.actions[7, 0, 0] = 1.0 + 1e-6  # float32 rounding of data scaled elsewhere
    assert CQL("MlpPolicy", "Pendulum-v1", dataset=buffer).replay_buffer.size() == 100
    buffer.actions[40, 0, 0] = 3.0
    buffer.actions[60, 0, 0] = np.nan
    with pytest.raises(DatasetError, match=r"actions hold nan at index 60: every value must be finite"):
        CQL("MlpPolicy", "Pendulum-v1", dataset=buffer)
    buffer.actions[60, 0, 0] = 0.0
    with pytest.raises(DatasetError, match=r"actions hold 3 at index 40 \(action\[0\]\), outside \[-1, 1\]"):
        CQL("MlpPolicy", "Pendulum-v1", dataset=buffer)
