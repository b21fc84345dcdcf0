"""The constructors' defaults on a tiny version of the offline suite's sparse mixture (``benchmarks/offline_suite.py``,
``mountaincar-mixture``): CQL learns its conservative weight by dual ascent towards a target gap, IQL reads raw
observations where CQL z-scores them, and each trains from the data as given."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql import BC, CQL, IQL
from sb3_cql.cql import NormalizedFlatten

TINY = {"net_arch": [32, 32]}


@pytest.fixture(scope="module")
def mixture() -> tuple[gym.Env, ReplayBuffer]:
    """Six 200-step MountainCarContinuous-v0 episodes: two of a bang-bang energy pump with N(0, 0.2) noise, four of
    pure N(0, 1) action noise (the suite's mixture, shortened), the sparse reward as the env gives it."""
    env = gym.make("MountainCarContinuous-v0", max_episode_steps=200)
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(1200, env.observation_space, env.action_space)
    for episode in range(6):
        observation, _ = env.reset(seed=episode)
        pump = episode < 2
        for _ in range(200):
            push = np.sign(observation[1]) if pump and observation[1] != 0 else 0.0
            noise = rng.normal(0.0, 0.2 if pump else 1.0)
            action = np.clip([push + noise], -1.0, 1.0).astype(np.float32)
            next_observation, reward, terminated, truncated, _ = env.step(action)
            buffer.add(observation, next_observation, action, np.array([reward]), np.array([terminated]),
                       [{"TimeLimit.truncated": truncated and not terminated}])  # fmt: skip
            observation = next_observation
            if terminated or truncated:
                break
    return env, buffer


@pytest.mark.parametrize("target, eased", [(10.0, True), (0.0, False)])
def test_cql_learns_its_conservative_weight_easing_it_while_the_gap_is_under_the_target(mixture, target, eased):
    """At the defaults (``cql_alpha`` 5, ``cql_target_action_gap`` 10, the multiplier's rate 1e-4) the Lagrange
    multiplier ``alpha'`` starts at 1 and falls while the critics' log-sum-exp gap stays under the target; with a target of 0 the same gap drives it
    up: the weight is learned from the data, not fixed."""
    env, buffer = mixture
    model = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, policy_kwargs=TINY, seed=0,
                **({} if target == 10.0 else {"cql_target_action_gap": target}))  # fmt: skip
    assert (model.cql_alpha, model.cql_target_action_gap, model.cql_alpha_learning_rate) == (5.0, target, 1e-4)
    assert model.alpha_prime().item() == pytest.approx(1.0)
    model.learn(100)
    gap = model.logger.name_to_value["train/cql_gap"]
    assert 0.0 < gap < 10.0
    # Adam moves log(alpha') by at most about its rate, 1e-4, a step: 0.01 in 100 steps
    assert (0.989 < model.alpha_prime().item() < 0.995) if eased else (1.005 < model.alpha_prime().item() < 1.011)


def test_a_fixed_weight_is_one_keyword_away_and_learns_no_multiplier(mixture):
    env, buffer = mixture
    model = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, policy_kwargs=TINY, seed=0, cql_alpha=10.0,
                cql_target_action_gap=None).learn(20)  # fmt: skip
    assert model.alpha_prime_optimizer is None
    assert "train/cql_alpha_prime" not in model.logger.name_to_value


def test_a_model_loads_with_the_other_form_of_the_weight_given_to_load(mixture, tmp_path):
    """A model trained with the learned weight loads and trains on with a fixed one (``cql_target_action_gap=None``
    to ``load``, as a config that fixes it does through the zoo's ``-i``), and a fixed-weight model with a target
    learns a multiplier from alpha' = 1; the networks come back as saved either way."""
    env, buffer = mixture
    learned = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, policy_kwargs=TINY, seed=0).learn(20)
    fixed = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, policy_kwargs=TINY, seed=0,
                cql_target_action_gap=None).learn(20)  # fmt: skip
    learned.save(tmp_path / "learned")
    fixed.save(tmp_path / "fixed")
    observations = buffer.observations[:10, 0]
    for name, model, options in (("learned", learned, {"cql_target_action_gap": None}),
                                 ("fixed", fixed, {"cql_target_action_gap": 10.0})):  # fmt: skip
        loaded = CQL.load(tmp_path / name, env=env, **options)
        np.testing.assert_array_equal(loaded.predict(observations, deterministic=True)[0],
                                      model.predict(observations, deterministic=True)[0])  # fmt: skip
        assert loaded.cql_target_action_gap == options["cql_target_action_gap"]
        assert (loaded.alpha_prime_optimizer is None) == (options["cql_target_action_gap"] is None)
        if loaded.alpha_prime_optimizer is not None:
            assert loaded.alpha_prime().item() == pytest.approx(1.0)
        loaded.replay_buffer = buffer
        loaded.learn(10, reset_num_timesteps=False)
        assert ("train/cql_alpha_prime" in loaded.logger.name_to_value) == (loaded.alpha_prime_optimizer is not None)


def test_iql_reads_raw_observations_and_cql_and_bc_z_score_them_by_default(mixture):
    """The suite's observation scales lie far apart (a velocity of 0.07 beside a position of 1); IQL's advantage
    weights fail a sparse task on z-scored ones, so IQL reads them raw, as the references do."""
    env, buffer = mixture
    models = {name: algorithm("MlpPolicy", env, dataset=buffer, batch_size=64, policy_kwargs=TINY, seed=0).learn(20)
              for name, algorithm in (("cql", CQL), ("iql", IQL), ("bc", BC))}  # fmt: skip
    normalised = {name: isinstance(model.actor.features_extractor, NormalizedFlatten) for name, model in models.items()}
    assert normalised == {"cql": True, "iql": False, "bc": True}
    observations = th.as_tensor(buffer.observations[: buffer.size(), 0])
    extractor = models["cql"].actor.features_extractor
    z_scored = extractor(observations)
    np.testing.assert_allclose(z_scored.mean(dim=0).numpy(), 0.0, atol=1e-4)
    np.testing.assert_allclose(z_scored.std(dim=0, unbiased=False).numpy(), 1.0, atol=1e-3)
    for model in models.values():
        actions, _ = model.predict(buffer.observations[:10, 0], deterministic=True)
        assert actions.shape == (10, 1) and np.all(np.isfinite(actions)) and np.all(np.abs(actions) <= 1.0)


def sparse_buffer(share: float, n: int = 2000) -> tuple[gym.Env, ReplayBuffer]:
    """Random 2-D states, a reward of 1 on ``share`` of the transitions (each ending its episode) and a small
    action cost on the rest: a sparse reward whose floor is not constant."""
    env = gym.make("MountainCarContinuous-v0")
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(n, env.observation_space, env.action_space)
    for index in range(n):
        observation = rng.uniform(-1.0, 0.5, 2).astype(np.float32)
        action = rng.uniform(-1.0, 1.0, 1).astype(np.float32)
        success = index < share * n
        reward = 1.0 if success else -0.001 * float(action[0] ** 2)
        buffer.add(observation, observation, action, np.array([reward]), np.array([success]), [{}])
    return env, buffer


@pytest.mark.parametrize(
    "options, share, warned",
    [({"cql_alpha": 10.0, "cql_target_action_gap": None}, 0.01, True),  # the setting that failed the sparse mixture
     ({}, 0.01, False),  # the learned weight
     ({"cql_alpha": 10.0, "cql_target_action_gap": None, "actor_bc_weight": 8.0}, 0.01, False),  # anchored: the Panda config's
     ({"cql_alpha": 1.0, "cql_target_action_gap": None}, 0.01, False),  # a fixed weight that solved it
     ({"cql_alpha": 10.0, "cql_target_action_gap": None}, 0.3, False)],  # a dense reward
)  # fmt: skip
def test_a_fixed_weight_that_failed_a_sparse_reward_is_warned_of_on_one_line(options, share, warned, recwarn):
    env, buffer = sparse_buffer(share)
    CQL("MlpPolicy", env, dataset=buffer, policy_kwargs=TINY, **options)
    messages = [str(warning.message) for warning in recwarn if "sparse reward" in str(warning.message)]
    if warned:
        assert len(messages) == 1 and "\n" not in messages[0]
        assert "cql_alpha=10" in messages[0] and "1.00% of the transitions" in messages[0]
        assert "cql_target_action_gap" in messages[0] and "actor_bc_weight" in messages[0]
    else:
        assert messages == []
