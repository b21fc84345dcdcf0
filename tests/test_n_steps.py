"""SB3's n-step returns in the offline algorithms: the data's buffers sample them within each episode, the TD target
bootstraps with their discounts, and one step is today's update exactly."""

import gymnasium as gym
import minari
import numpy as np
import pandas as pd
import pytest
import rollouts
import torch as th
from gymnasium import spaces
from rollouts import random_rollouts
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.logger import configure

from sb3_cql import BC, CQL, CalQL
from sb3_cql.common import MixedReplayBuffer, ReturnToGoReplayBuffer
from sb3_cql.data import fill_replay_buffer

TINY = {"net_arch": [16]}
OBSERVATIONS = spaces.Box(-10.0, 10.0, shape=(1,), dtype=np.float32)
ACTIONS = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
GAMMA = 0.5
#: Hand-made episodes: (rewards, how it ends). Observation t of an episode holds 10 * episode + t (to find it again).
EPISODES = [([1.0, 2.0, 4.0, 8.0], "terminated"), ([1.0, 1.0, 1.0], "truncated"), ([3.0], "terminated")]


def hand_made_buffer() -> ReplayBuffer:
    buffer = ReplayBuffer(16, OBSERVATIONS, ACTIONS)
    for episode, (rewards, end) in enumerate(EPISODES):
        for step, reward in enumerate(rewards):
            last = step == len(rewards) - 1
            observation, next_observation = np.array([10 * episode + step]), np.array([10 * episode + step + 1])
            buffer.add(observation, next_observation, np.zeros(1), np.array([reward]), np.array([last]),
                       [{"TimeLimit.truncated": last and end == "truncated"}])  # fmt: skip
    return buffer


def expected_samples(n_steps: int) -> list[tuple[float, float, float, float, float]]:
    """(observation, n-step reward, discount, done, next observation) of every transition, by hand."""
    rows = []
    for episode, (rewards, end) in enumerate(EPISODES):
        for step in range(len(rewards)):
            summed = rewards[step : step + n_steps]  # cut at the episode's end
            reward = sum(GAMMA**k * r for k, r in enumerate(summed))
            reaches_end = step + len(summed) == len(rewards)
            done = float(reaches_end and end == "terminated")  # a truncation bootstraps
            rows.append((10 * episode + step, reward, GAMMA ** len(summed), done, 10 * episode + step + len(summed)))
    return rows


def all_samples(buffer: ReplayBuffer) -> list[tuple[float, ...]]:
    samples = buffer._get_samples(np.arange(buffer.size()))
    discounts = samples.discounts if samples.discounts is not None else th.full_like(samples.rewards, GAMMA)
    columns = (samples.observations, samples.rewards, discounts, samples.dones, samples.next_observations)
    return [tuple(float(column[row, 0]) for column in columns) for row in range(buffer.size())]


def spaces_env() -> gym.Env:
    return rollouts.spaces_env(OBSERVATIONS, ACTIONS)


@pytest.mark.parametrize("n_steps", [1, 2, 3, 5])
def test_the_datas_n_step_rewards_and_discounts_are_the_hand_computed_ones(n_steps, tmp_path, monkeypatch):
    """Terminated, truncated and shorter-than-n episodes, from a given ReplayBuffer as from a Minari dataset's load."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    model = CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), n_steps=n_steps, gamma=GAMMA, batch_size=2,
                policy_kwargs=TINY, normalize_observations=False)  # fmt: skip
    assert isinstance(model.replay_buffer, NStepReplayBuffer) == (n_steps > 1)
    np.testing.assert_allclose(all_samples(model.replay_buffer), expected_samples(n_steps), rtol=1e-6)
    filled = fill_replay_buffer(
        hand_made_minari_dataset(tmp_path), OBSERVATIONS, ACTIONS, replay_buffer_class=model.replay_buffer_class,
        replay_buffer_kwargs=model.replay_buffer_kwargs,
    )  # fmt: skip
    assert type(filled) is model.replay_buffer_class
    np.testing.assert_allclose(all_samples(filled), expected_samples(n_steps), rtol=1e-6)


def hand_made_minari_dataset(folder) -> "minari.MinariDataset":
    """The hand-made episodes as a Minari dataset."""
    episodes = []
    for episode, (rewards, end) in enumerate(EPISODES):
        length = len(rewards)
        terminations, truncations = np.zeros(length, bool), np.zeros(length, bool)
        (terminations if end == "terminated" else truncations)[-1] = True
        episodes.append(minari.data_collector.EpisodeBuffer(
            observations=np.arange(10 * episode, 10 * episode + length + 1, dtype=np.float32).reshape(-1, 1),
            actions=np.zeros((length, 1), dtype=np.float32), rewards=np.array(rewards), terminations=terminations,
            truncations=truncations,
        ))  # fmt: skip
    return minari.create_dataset_from_buffers("test/hand-made-v0", episodes, env=spaces_env(), algorithm_name="test",
                                              author="t", author_email="t", code_permalink="t", description="t")  # fmt: skip


def test_the_td_target_bootstraps_with_the_samples_discounts_and_sums_the_reward_bias_over_their_steps():
    model = CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), n_steps=3, gamma=GAMMA, batch_size=2,
                reward_scale=4.0, reward_bias=-2.0, policy_kwargs=TINY, normalize_observations=False)  # fmt: skip
    data = model.replay_buffer._get_samples(np.arange(8))
    next_policy = model.actor.get_action_dist_params(data.next_observations)[:2]
    with th.no_grad():
        th.manual_seed(0)
        target = model.compute_target(data, next_policy, th.ones(1), data.discounts)
        th.manual_seed(0)
        next_values = model.next_state_values(data.next_observations, next_policy, th.ones(1))
    for row, (observation, _, discount, done, _) in enumerate(expected_samples(3)):
        rewards, _ = EPISODES[int(observation) // 10]
        step = int(observation) % 10
        critic_rewards = sum(GAMMA**k * (4.0 * r - 2.0) for k, r in enumerate(rewards[step : step + 3]))
        expected = critic_rewards + (1 - done) * discount * float(next_values[row, 0])
        assert float(target[row, 0]) == pytest.approx(expected, rel=1e-5)


def test_one_step_returns_are_the_plain_buffers_update_exactly(tmp_path):
    """``n_steps=1`` keeps SB3's plain ReplayBuffer and ``gamma``; an explicit one-step NStepReplayBuffer, whose samples
    carry ``discounts = gamma``, trains to the same losses."""
    losses = {}
    for name, buffer_class in (("plain", None), ("n-step", NStepReplayBuffer)):
        model = CQL("MlpPolicy", spaces_env(), dataset=hand_made_minari_dataset_buffer(buffer_class), gamma=GAMMA,
                    batch_size=4, bc_steps=5, actor_bc_weight=1.0, policy_kwargs=TINY, seed=0)  # fmt: skip
        assert type(model.replay_buffer) is (buffer_class or ReplayBuffer)
        model.set_logger(configure(str(tmp_path / name), ["csv"]))
        model.learn(12, log_interval=1)
        logs = pd.read_csv(tmp_path / name / "progress.csv")
        losses[name] = logs[sorted(key for key in logs.columns if key.startswith("train/"))]
    assert {"train/critic_loss", "train/actor_loss", "train/cql_loss"} <= set(losses["plain"].columns)
    assert len(losses["plain"]) == 12
    pd.testing.assert_frame_equal(losses["plain"], losses["n-step"], check_exact=True)


def hand_made_minari_dataset_buffer(buffer_class: type[ReplayBuffer] | None) -> ReplayBuffer:
    buffer = hand_made_buffer()
    if buffer_class is None:
        return buffer
    n_step = buffer_class(buffer.buffer_size, OBSERVATIONS, ACTIONS, n_steps=1, gamma=GAMMA)
    for field in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        getattr(n_step, field)[:] = getattr(buffer, field)
    n_step.pos = buffer.pos
    return n_step


def test_calibrated_samples_carry_the_whole_episodes_return_to_go_beside_the_n_step_returns():
    model = CalQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), n_steps=2, gamma=GAMMA, batch_size=2,
                  policy_kwargs=TINY, normalize_observations=False)  # fmt: skip
    buffer = model.replay_buffer
    assert isinstance(buffer, ReturnToGoReplayBuffer) and buffer.n_steps == 2
    samples = buffer._get_samples(np.arange(8))
    assert [float(value) for value in samples.rewards[:, 0]] == pytest.approx([row[1] for row in expected_samples(2)])
    assert [float(value) for value in samples.discounts[:, 0]] == pytest.approx([row[2] for row in expected_samples(2)])
    # Episode 0 terminated: G = 1 + 0.5 * 2 + 0.25 * 4 + 0.125 * 8 from its first state.
    assert float(samples.returns_to_go[0, 0]) == pytest.approx(4.0)


def test_fine_tuning_with_n_steps_samples_n_step_returns_online_and_offline():
    model = CalQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(400), n_steps=3, batch_size=32, policy_kwargs=TINY,
                  online_fraction=0.5, seed=0)  # fmt: skip
    model.learn(250)  # more than one episode of 200 steps
    buffer = model.replay_buffer
    assert isinstance(buffer, MixedReplayBuffer) and buffer.online.n_steps == buffer.offline.n_steps == 3
    assert buffer.online.size() == 250 and buffer.pos == 250
    samples = buffer.sample(32)
    assert samples.discounts.shape == (32, 1) and th.all(samples.discounts <= model.gamma)
    assert th.isfinite(samples.returns_to_go[:16]).all()  # the offline episodes have ended


def pendulum_buffer(n_transitions: int) -> ReplayBuffer:
    return random_rollouts(gym.make("Pendulum-v1"), n_transitions)


def test_bc_takes_n_steps_and_a_reward_bias_with_n_steps_needs_a_discount():
    model = BC("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), n_steps=3, batch_size=2, policy_kwargs=TINY)
    assert isinstance(model.replay_buffer, NStepReplayBuffer) and model.replay_buffer.n_steps == 3
    model.learn(3)
    with pytest.raises(ValueError, match="needs gamma < 1"):
        CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), n_steps=3, gamma=1.0, reward_bias=-1.0)


def test_a_saved_n_step_model_loads_without_sb3s_custom_buffer_warning(tmp_path, recwarn):
    model = CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), n_steps=3, gamma=GAMMA, batch_size=2,
                policy_kwargs=TINY)  # fmt: skip
    model.save(tmp_path / "model.zip")
    loaded = CQL.load(tmp_path / "model.zip", env=spaces_env())
    assert not [warning for warning in recwarn if "n_steps" in str(warning.message)]
    assert loaded.n_steps == 3 and loaded.replay_buffer_class is NStepReplayBuffer


@pytest.mark.parametrize("saved, given", [(1, 4), (3, 1)])
def test_n_steps_given_to_load_sets_the_loaded_models_returns(saved, given, tmp_path, monkeypatch):
    """As the zoo's fine-tuning config passes its hyperparameters to load: the data reload into the buffer SB3 chooses
    for the new n_steps, and the online transitions go to one of the same."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    hand_made_minari_dataset(tmp_path)
    model = CQL("MlpPolicy", spaces_env(), dataset="test/hand-made-v0", n_steps=saved, gamma=GAMMA, batch_size=2,
                policy_kwargs=TINY)  # fmt: skip
    model.save(tmp_path / "model.zip")
    loaded = CQL.load(tmp_path / "model.zip", env=spaces_env(), n_steps=given, online_fraction=0.5)
    loaded.learn(3)
    assert getattr(loaded.replay_buffer.offline, "n_steps", 1) == getattr(loaded.replay_buffer.online, "n_steps", 1) == given
    np.testing.assert_allclose(all_samples(loaded.replay_buffer.offline), expected_samples(given), rtol=1e-6)
