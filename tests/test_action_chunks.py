"""Action chunks (Q-chunking): the data read as the chunk from every step, cut at an episode's end; the actor and the
critics on chunks; each chunk run open loop when the model acts, offline evaluation and online fine-tuning alike."""

import gymnasium as gym
import numpy as np
import pytest
import rollouts
import torch as th
from gymnasium import spaces
from rollouts import random_rollouts
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_cql import BC, CQL, CalQL
from sb3_cql.common import ActionChunkReplayBuffer, MixedReplayBuffer
from sb3_cql.common.policies import OfflinePolicy

TINY = {"net_arch": [16]}
OBSERVATIONS = spaces.Box(-100.0, 100.0, shape=(1,), dtype=np.float32)
ACTIONS = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
GAMMA = 0.5
#: Hand-made episodes: (length, how it ends); step t of episode e has observation 10 e + t, action (e, t) / 10, reward t.
EPISODES = [(5, "terminated"), (2, "truncated"), (4, "under way")]


def hand_made_buffer() -> ReplayBuffer:
    buffer = ReplayBuffer(32, OBSERVATIONS, ACTIONS)
    for episode, (length, end) in enumerate(EPISODES):
        for step in range(length):
            last = step == length - 1 and end != "under way"
            buffer.add(np.array([10 * episode + step]), np.array([10 * episode + step + 1]),
                       np.array([episode, step]) / 10, np.array([float(step)]), np.array([last]),
                       [{"TimeLimit.truncated": last and end == "truncated"}])  # fmt: skip
    return buffer


def spaces_env() -> gym.Env:
    return rollouts.spaces_env(OBSERVATIONS, ACTIONS)


def test_every_step_starts_a_chunk_cut_at_its_episodes_end_with_its_n_step_return():
    chunk = 3
    model = CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), action_chunk=chunk, gamma=GAMMA, batch_size=2,
                policy_kwargs=TINY, normalize_observations=False)  # fmt: skip
    buffer = model.replay_buffer
    assert isinstance(buffer, ActionChunkReplayBuffer) and buffer.n_steps == chunk and model.n_steps == chunk
    rows = np.arange(buffer.size())
    samples = buffer._get_samples(rows)
    row = 0
    for episode, (length, end) in enumerate(EPISODES):
        for step in range(length):
            steps = list(range(step, min(step + chunk, length)))  # cut at the episode's end (or the last row written)
            padded = steps + [steps[-1]] * (chunk - len(steps))  # the last action repeated
            expected_actions = np.concatenate([np.array([episode, t]) / 10 for t in padded])
            np.testing.assert_allclose(samples.actions[row].numpy(), expected_actions, rtol=1e-6)
            assert float(samples.rewards[row, 0]) == pytest.approx(sum(GAMMA**k * t for k, t in enumerate(steps)))
            assert float(samples.discounts[row, 0]) == pytest.approx(GAMMA ** len(steps))
            ends = step + len(steps) == length
            assert float(samples.dones[row, 0]) == float(ends and end == "terminated")
            row += 1
    single = buffer.single_step_samples(8)
    assert single.actions.shape == (8, 2) and single.discounts is None  # SB3's own sampling of the same transitions


def test_the_actor_and_the_critics_work_on_chunks_while_the_model_keeps_the_envs_action_space():
    model = CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), action_chunk=3, batch_size=4, policy_kwargs=TINY)
    assert isinstance(model.policy, OfflinePolicy) and model.action_space.shape == model.policy.action_space.shape == (2,)
    assert model.actor.action_space.shape == (6,) and model.critic.q_networks[0][0].in_features == 1 + 6
    assert model.target_entropy == -6.0  # SAC's -|A| for the whole chunk
    model.learn(5)
    with pytest.raises(ValueError, match="n_steps=2 with action_chunk=3"):
        CQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), action_chunk=3, n_steps=2)
    with pytest.raises(ValueError, match="CalQL does not support action_chunk > 1"):
        CalQL("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), action_chunk=3)
    with pytest.raises(ValueError, match="action_chunk must be an integer >= 1, got 0"):
        BC("MlpPolicy", spaces_env(), dataset=hand_made_buffer(), action_chunk=0)


def test_predict_runs_each_chunk_open_loop_through_sb3s_state():
    model = BC("MlpPolicy", "Pendulum-v1", dataset=random_rollouts(gym.make("Pendulum-v1"), 300), action_chunk=4,
               batch_size=16, policy_kwargs=TINY, seed=0)  # fmt: skip
    model.learn(10)
    observations = np.random.default_rng(0).standard_normal((6, 3)).astype(np.float32)
    first, state = model.predict(observations[0], deterministic=True)
    chunk = state[0][0]  # the whole chunk predicted at the first observation
    assert chunk.shape == (4, 1) and np.allclose(first, chunk[0])
    actions = [first]
    for observation in observations[1:4]:  # later observations do not change the chunk under way
        action, state = model.predict(observation, state=state, deterministic=True)
        actions.append(action)
    np.testing.assert_allclose(np.stack(actions), chunk)
    action, state = model.predict(observations[4], state=state, deterministic=True)  # used up: a new chunk
    np.testing.assert_allclose(action, model.predict(observations[4], deterministic=True)[0])
    _, restarted = model.predict(observations[5], state=state, episode_start=np.array([True]), deterministic=True)
    assert restarted[1].tolist() == [1]  # an episode start begins a new chunk
    batch, batch_state = model.predict(observations[:3], deterministic=True)  # a batch of envs, one chunk each
    assert batch.shape == (3, 1) and batch_state[0].shape == (3, 4, 1)


def test_a_chunked_model_trains_evaluates_saves_and_loads(tmp_path):
    env = gym.make("Pendulum-v1")
    model = CQL("MlpPolicy", env, dataset=random_rollouts(gym.make("Pendulum-v1"), 300), action_chunk=5, batch_size=16,
                cql_n_actions=2, policy_kwargs=TINY, seed=0)  # fmt: skip
    model.learn(20, callback=EvalCallback(gym.make("Pendulum-v1"), eval_freq=10, n_eval_episodes=1, warn=False))
    model.save(tmp_path / "chunked.zip")
    loaded = CQL.load(tmp_path / "chunked.zip", env=gym.make("Pendulum-v1"))
    assert loaded.action_chunk == loaded.policy.action_chunk == 5  # read from the saved model
    returns = []
    for policy in (model, loaded):
        env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
        env.seed(0)
        returns.append(evaluate_policy(policy, env, n_eval_episodes=1, warn=False)[0])
    assert returns[0] == pytest.approx(returns[1])


def test_fine_tuning_runs_chunks_open_loop_and_starts_a_new_one_at_each_episode(monkeypatch):
    """Pendulum's episodes are 200 steps: with chunks of 3, 67 chunks an episode (the last one cut at the end)."""
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_rollouts(gym.make("Pendulum-v1"), 300), action_chunk=3,
                online_fraction=0.5, online_buffer_size=1000, batch_size=16, cql_n_actions=2, policy_kwargs=TINY,
                seed=0)  # fmt: skip
    predict, new_chunks = model.policy.predict, []

    def counting(*args, **kwargs):
        actions, state = predict(*args, **kwargs)
        new_chunks.append(int(state[1][0]) == 1)
        return actions, state

    monkeypatch.setattr(model.policy, "predict", counting)
    model.learn(250)
    assert len(new_chunks) == 250 and sum(new_chunks) == 67 + 17
    buffer = model.replay_buffer
    assert isinstance(buffer, MixedReplayBuffer) and isinstance(buffer.online, ActionChunkReplayBuffer)
    assert buffer.online.size() == 250 and buffer.sample(8).actions.shape == (8, 3)
    assert th.isfinite(buffer.sample(8).rewards).all()
