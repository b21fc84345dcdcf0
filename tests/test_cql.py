"""CQL: offline training through SB3's API, the conservative property, save/load (whole or not at all), bad input."""

import io
import re
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.logger import Logger, configure
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import load_from_pkl

from sb3_cql import BC, CQL
from sb3_cql.common import KeywordError, MixedReplayBuffer, ReturnToGoReplayBuffer, SettingError
from sb3_cql.common.allocator import retain_freed_memory
from sb3_cql.cql import CalQL, NormalizedFlatten
from sb3_cql.cql.fused_mlp import relu_mlp, relu_mlp_parameters
from sb3_cql.data import CollectionSpec, DatasetError, collect_dataset

TINY = {"net_arch": [32, 32]}


def random_pendulum_buffer(n_transitions: int = 1000, seed: int = 0) -> ReplayBuffer:
    env = gym.make("Pendulum-v1")
    env.action_space.seed(seed)
    buffer = ReplayBuffer(n_transitions, env.observation_space, env.action_space)
    observation, _ = env.reset(seed=seed)
    for _ in range(n_transitions):
        action = env.action_space.sample()
        next_observation, reward, terminated, truncated, _ = env.step(action)
        buffer.add(observation, next_observation, action / 2.0, np.array([reward]), np.array([terminated]),
                   [{"TimeLimit.truncated": truncated}])  # fmt: skip
        observation = next_observation if not (terminated or truncated) else env.reset()[0]
    return buffer


def test_cql_is_an_sb3_off_policy_algorithm_trained_offline(tmp_path):
    buffer = random_pendulum_buffer()
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=32, policy_kwargs=TINY, seed=0)
    assert isinstance(model, OffPolicyAlgorithm) and model.replay_buffer is buffer
    model.set_logger(configure(str(tmp_path / "logs"), ["csv"]))
    eval_callback = EvalCallback(gym.make("Pendulum-v1"), eval_freq=100, n_eval_episodes=1, log_path=str(tmp_path / "eval"))
    checkpoints = CheckpointCallback(save_freq=100, save_path=str(tmp_path / "checkpoints"))
    before = buffer.observations.copy()
    model.learn(200, callback=[eval_callback, checkpoints], log_interval=50, progress_bar=True)

    assert model.num_timesteps == 200 and model._n_updates == 200
    np.testing.assert_array_equal(buffer.observations, before)  # offline: no transition was added
    assert np.load(tmp_path / "eval" / "evaluations.npz")["timesteps"].tolist() == [100, 200]
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["rl_model_100_steps.zip", "rl_model_200_steps.zip"]
    logged = pd.read_csv(tmp_path / "logs" / "progress.csv")
    for key in ("train/critic_loss", "train/actor_loss", "train/ent_coef", "train/cql_loss", "train/cql_q_random",
                "train/cql_q_policy", "train/cql_q_data", "eval/mean_reward", "time/gradient_steps_per_s"):  # fmt: skip
        assert key in logged.columns, key
    assert sorted(set(logged["time/total_timesteps"].dropna())) == [50, 100, 150, 200]  # EvalCallback dumps too


@pytest.mark.parametrize("options", [{}, {"cql_target_action_gap": 5.0}, {"cql_max_backup": True, "bc_steps": 20},
                                     {"cql_deterministic_backup": False, "ent_coef": 0.1},
                                     {"calibrated": True, "reward_scale": 2.0}])  # fmt: skip
def test_save_and_load_round_trip(tmp_path, options):
    env = gym.make("Pendulum-v1")
    options = dict(options)
    algorithm = CalQL if options.pop("calibrated", False) else CQL
    model = algorithm("MlpPolicy", env, dataset=random_pendulum_buffer(), batch_size=32, policy_kwargs=TINY, seed=1,
                      **options)  # fmt: skip
    model.learn(50)
    model.save(tmp_path / "cql")
    loaded = algorithm.load(tmp_path / "cql", env=env)
    assert loaded.replay_buffer.buffer_size == 1  # predicting needs no training buffer
    observations = np.stack([env.observation_space.sample() for _ in range(16)])
    np.testing.assert_array_equal(loaded.predict(observations, deterministic=True)[0],
                                  model.predict(observations, deterministic=True)[0])  # fmt: skip
    for name, tensor in model.policy.state_dict().items():
        th.testing.assert_close(loaded.policy.state_dict()[name], tensor)
    if "cql_target_action_gap" in options:
        assert model.log_alpha_prime.item() != 0.0
        th.testing.assert_close(loaded.log_alpha_prime, model.log_alpha_prime)
        assert loaded.alpha_prime_optimizer.state_dict()["state"]
    if algorithm is CalQL:
        assert type(loaded) is CalQL and isinstance(loaded.replay_buffer, ReturnToGoReplayBuffer)
        model.save_replay_buffer(tmp_path / "buffer")
        loaded.load_replay_buffer(tmp_path / "buffer")
        np.testing.assert_array_equal(loaded.replay_buffer.returns_to_go, model.replay_buffer.returns_to_go)
        assert loaded.replay_buffer.reward_scale == 2.0
    loaded.replay_buffer = model.replay_buffer
    loaded.learn(10, reset_num_timesteps=False)
    assert loaded.num_timesteps == 60


def test_observations_are_normalised_with_the_dataset_statistics(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = collect_dataset(CollectionSpec(n_episodes=2), progress_bar=False)
    model = CQL("MlpPolicy", "Panda-v0", dataset="sb3cql/Panda-v0/pid-v0", batch_size=32, policy_kwargs=TINY)
    assert model.replay_buffer.size() == dataset.total_steps
    observations = model.replay_buffer.observations[: model.replay_buffer.size(), 0]
    for module in (model.actor, model.critic, model.critic_target):
        extractor = module.features_extractor
        assert isinstance(extractor, NormalizedFlatten)
        np.testing.assert_allclose(extractor.mean.numpy(), observations.mean(axis=0), rtol=1e-5, atol=1e-6)
    normalised = model.actor.features_extractor(th.as_tensor(observations)).numpy()
    varying = observations.std(axis=0) > 1e-3  # a constant feature keeps a std floor of 1e-6
    np.testing.assert_allclose(normalised.mean(axis=0)[varying], 0.0, atol=1e-3)
    np.testing.assert_allclose(normalised.std(axis=0)[varying], 1.0, atol=1e-3)


def test_dataset_that_does_not_fit_the_env_is_rejected(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    collect_dataset(CollectionSpec(n_episodes=1), progress_bar=False)
    with pytest.raises(DatasetError, match="sb3cql/Panda-v0/pid-v0"):
        CQL("MlpPolicy", "Pendulum-v1", dataset="sb3cql/Panda-v0/pid-v0")
    with pytest.raises(ValueError, match="do not match"):
        CQL("MlpPolicy", "Panda-v0", dataset=random_pendulum_buffer(100))


def test_too_little_data_is_rejected():
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(20), batch_size=32, policy_kwargs=TINY)
    with pytest.raises(ValueError, match="batch_size=32"):
        model.learn(10)


def test_divergence_stops_with_the_step():
    buffer = random_pendulum_buffer(100)
    buffer.rewards[50] = 3e38  # finite, but its square is not
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=100, policy_kwargs=TINY)
    with pytest.raises(FloatingPointError, match="gradient step 1") as error:
        model.learn(5)
    assert isinstance(error.value, ValueError)  # the zoo's tuning prunes such a trial


class OneStepBandit(gym.Env):
    """One state, one step: reward 1 - a^2 for a 1-D action in [-1, 1]."""

    observation_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
    action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(1, dtype=np.float32), {}

    def step(self, action):
        return np.zeros(1, dtype=np.float32), float(1.0 - action[0] ** 2), True, False, {}


def test_cql_is_conservative_where_sac_overestimates():
    """The data cover only a in [-1, -0.5]; on unseen actions a in [0.5, 1], CQL's Q stays below its Q on the data,
    while SAC trained on the same data extrapolates higher."""
    env = OneStepBandit()
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(2000, env.observation_space, env.action_space)
    for action in rng.uniform(-1.0, -0.5, size=2000):
        buffer.add(np.zeros(1), np.zeros(1), np.array([action]), np.array([1 - action**2]), np.array([True]), [{}])
    data_actions = th.linspace(-1.0, -0.5, 20).reshape(-1, 1)
    unseen_actions = th.linspace(0.5, 1.0, 20).reshape(-1, 1)
    observations = th.zeros(20, 1)

    def mean_q(model, actions):
        with th.no_grad():
            return th.cat(model.critic(observations, actions), dim=1).min(dim=1).values.mean().item()

    cql = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, learning_rate=1e-3, actor_learning_rate=1e-3,
              policy_kwargs=TINY, seed=0)  # fmt: skip
    cql.learn(1000)
    sac = SAC("MlpPolicy", env, batch_size=64, learning_rate=1e-3, policy_kwargs=TINY, seed=0, learning_starts=0)
    sac.replay_buffer = buffer
    sac.set_logger(Logger(None, []))
    sac.train(gradient_steps=1000, batch_size=64)
    assert mean_q(cql, unseen_actions) < mean_q(cql, data_actions)
    assert (
        mean_q(sac, unseen_actions) - mean_q(sac, data_actions) > mean_q(cql, unseen_actions) - mean_q(cql, data_actions) + 1.0
    )


def failing_chain_buffer(gamma: float) -> tuple[ReplayBuffer, float]:
    """100 episodes of 20 steps with reward -1, cut by the time limit, actions near 0.5 * s[0]: every state's
    return-to-go is -1 / (1 - gamma)."""
    rng = np.random.default_rng(0)
    observation_space, action_space = spaces.Box(-1.0, 1.0, (2,), np.float32), spaces.Box(-1.0, 1.0, (1,), np.float32)
    buffer = ReplayBuffer(2000, observation_space, action_space)
    for _ in range(100):
        observation = rng.uniform(-1.0, 1.0, 2).astype(np.float32)
        for step in range(20):
            action = np.clip(0.5 * observation[:1] + 0.05 * rng.standard_normal(1), -1.0, 1.0)
            next_observation = np.clip(observation + 0.1 * rng.standard_normal(2), -1.0, 1.0).astype(np.float32)
            buffer.add(observation, next_observation, action, np.array([-1.0]), np.array([step == 19]),
                       [{"TimeLimit.truncated": step == 19}])  # fmt: skip
            observation = next_observation
    return buffer, -1.0 / (1.0 - gamma)


def q_at_policy_actions(model: CQL, observations: th.Tensor, n: int = 10) -> th.Tensor:
    """The lower critic's value of ``n`` policy samples at each observation."""
    with th.no_grad():
        actions, _ = model.sample_policy_actions(*model.actor.get_action_dist_params(observations)[:2], n)
        return th.cat(model.critic(observations.repeat_interleave(n, dim=0), actions), dim=1).min(dim=1).values


@pytest.mark.slow
def test_calibrated_values_stay_at_the_data_return_where_cql_sinks_below():
    """Plain CQL pushes Q at the policy's actions far below the return the data earned; Cal-QL keeps it at or above
    (tolerance: 10% of the return)."""
    buffer, data_return = failing_chain_buffer(gamma=0.9)
    observations = th.as_tensor(buffer.observations[:500, 0])
    means = {}
    for calibrated in (False, True):
        model = (CalQL if calibrated else CQL)("MlpPolicy", spaces_env(buffer), dataset=buffer, gamma=0.9, batch_size=64,
                                               learning_rate=1e-3, cql_alpha=10.0, policy_kwargs=TINY, seed=0)  # fmt: skip
        model.learn(3000)
        means[calibrated] = q_at_policy_actions(model, observations).mean().item()
    assert means[False] < data_return - 5.0  # measured: -22.2 (return -10)
    assert means[True] >= data_return + 0.1 * data_return  # measured: -8.5


def spaces_env(buffer: ReplayBuffer) -> gym.Env:
    """An env with the buffer's spaces (SB3 needs one; offline training never steps it)."""

    class SpacesEnv(gym.Env):
        observation_space, action_space = buffer.observation_space, buffer.action_space

        def reset(self, *, seed=None, options=None):
            return self.observation_space.sample(), {}

        def step(self, action):
            return self.observation_space.sample(), 0.0, False, True, {}

    return SpacesEnv()


def test_calibration_lifts_the_policy_groups_to_the_bound_and_logs_how_often(tmp_path):
    """The conservative term sees max(Q, G) at the policy's actions: with a return-to-go far above every value the
    log-sum-exp is the bound's; with none (-inf, an episode under way) it is plain CQL's."""
    buffer, _ = failing_chain_buffer(gamma=0.9)
    model = CalQL("MlpPolicy", spaces_env(buffer), dataset=buffer, gamma=0.9, batch_size=64, policy_kwargs=TINY, seed=0)
    assert isinstance(model.replay_buffer, ReturnToGoReplayBuffer)
    np.testing.assert_allclose(model.replay_buffer.returns_to_go[: buffer.size()], -10.0, rtol=1e-6)
    data = model.replay_buffer.sample(64)
    policy = model.actor.get_action_dist_params(data.observations)[:2]
    policy = (policy[0].detach(), policy[1].detach())
    actions, log_densities = model.sample_conservative_actions(data, policy, policy)
    q_data, q_sampled = model.q_values_at_data_and_sampled_actions(data, actions)
    gaps = {}
    for name, bound in (("high", 1000.0), ("none", -np.inf)):
        logged = {}
        gap = model.conservative_gaps(q_data, q_sampled, log_densities, data._replace(returns_to_go=th.full((64, 1), bound)),
                                      logged)  # fmt: skip
        gaps[name] = (gap[0].item(), logged["train/cql_bound_rate"][0])
    plain_cql = CQL("MlpPolicy", spaces_env(buffer), dataset=buffer, gamma=0.9, batch_size=64, policy_kwargs=TINY)
    logged = {}
    plain = plain_cql.conservative_gaps(q_data, q_sampled, log_densities, data, logged)[0].item()
    assert "train/cql_bound_rate" not in logged
    assert gaps["high"][0] > 1000.0 and gaps["high"][1] == 1.0  # every policy-action value lifted
    assert gaps["none"] == (pytest.approx(plain, rel=1e-6), 0.0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(20, log_interval=10)
    assert "train/cql_bound_rate" in pd.read_csv(tmp_path / "progress.csv").columns


def test_calql_is_built_directly_and_its_models_load_with_their_class(tmp_path):
    """``CalQL(...)`` is calibrated from construction (its buffer holds returns-to-go); its saved model loads with
    ``CalQL.load``, and ``CQL.load`` refuses it in one line naming the class to load it with; a plain CQL model loads as
    a CalQL (to fine-tune it calibrated); CQL takes no keyword that would make it another class."""
    buffer = random_pendulum_buffer(400)
    model = CalQL("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=32, policy_kwargs=TINY, seed=3).learn(30)
    assert isinstance(model.replay_buffer, ReturnToGoReplayBuffer)
    model.save(tmp_path / "calibrated")
    assert type(CalQL.load(tmp_path / "calibrated")) is CalQL
    with pytest.raises(SettingError, match=r"holds a CalQL model: load it with CalQL\.load \(in the zoo, --algo calql\)$"):
        CQL.load(tmp_path / "calibrated")
    plain = CQL("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=32, policy_kwargs=TINY, seed=3)
    assert type(plain.replay_buffer) is ReplayBuffer
    plain.save(tmp_path / "plain")
    assert type(CQL.load(tmp_path / "plain")) is CQL and type(CalQL.load(tmp_path / "plain")) is CalQL
    with pytest.raises(KeywordError, match="cql_calibrated"):
        CQL("MlpPolicy", "Pendulum-v1", dataset=buffer, cql_calibrated=True)


def test_online_fine_tuning_keeps_the_offline_data_and_continues_from_its_saved_transitions(tmp_path):
    """With ``online_fraction``, ``learn`` is SAC's: env steps, new transitions in the online part of the buffer
    beside the untouched offline data, returns-to-go for each ended episode; the saved buffer holds the online
    transitions, and a loaded model continues with them."""
    offline = random_pendulum_buffer(400)
    env = gym.make("Pendulum-v1")  # episodes of 200 steps
    model = CalQL("MlpPolicy", env, dataset=offline, batch_size=32, policy_kwargs=TINY, online_fraction=0.5,
                  online_buffer_size=5_000, seed=0)  # fmt: skip
    before = model.replay_buffer.observations.copy()
    model.set_logger(configure(str(tmp_path / "logs"), ["csv"]))
    model.learn(450, log_interval=1)
    buffer = model.replay_buffer
    assert isinstance(buffer, MixedReplayBuffer) and isinstance(buffer.online, ReturnToGoReplayBuffer)
    assert model.num_timesteps == 450 and model._n_updates == 450  # one gradient step per env step
    assert (buffer.offline.size(), buffer.online.size(), buffer.online.buffer_size) == (400, 450, 5_000)
    np.testing.assert_array_equal(buffer.offline.observations, before)
    finite = np.isfinite(buffer.online.returns_to_go[:450, 0])
    assert finite[:400].all() and not finite[400:].any()  # two episodes ended, the third is under way
    logged = pd.read_csv(tmp_path / "logs" / "progress.csv")
    assert {"rollout/ep_rew_mean", "train/cql_bound_rate", "time/fps"} <= set(logged.columns)

    model.save(tmp_path / "tuned")
    model.save_replay_buffer(tmp_path / "tuned_buffer")
    loaded = CalQL.load(tmp_path / "tuned", env=env)
    loaded.load_replay_buffer(tmp_path / "tuned_buffer")
    with pytest.raises(ValueError, match="batch_size=32 offline transitions or more"):  # no dataset id to reload
        loaded.learn(10)
    loaded.replay_buffer.set_offline(buffer.offline)
    loaded.learn(100)
    assert loaded.replay_buffer.online.size() == 550 and loaded.online_fraction == 0.5
    assert np.isfinite(loaded.replay_buffer.online.returns_to_go[400:550, 0]).sum() == 0  # the cut episode: no bound


def test_deterministic_rollouts_act_with_the_deterministic_action_plus_the_action_noise():
    """SAC acts with a sample of its policy; with ``deterministic_rollouts`` fine-tuning acts as TD3 does: the
    deterministic action, plus ``action_noise``. (No gradient steps: the policy stays the one that acted.)"""
    offline, env = random_pendulum_buffer(400), gym.make("Pendulum-v1")  # actions in [-2, 2], stored scaled to [-1, 1]

    def acted_minus_deterministic(**kwargs) -> np.ndarray:
        model = CQL("MlpPolicy", env, dataset=offline, batch_size=32, policy_kwargs=TINY, online_fraction=0.5,
                    online_buffer_size=1_000, gradient_steps=0, seed=0, **kwargs)  # fmt: skip
        model.learn(100)
        online = model.replay_buffer.online
        assert online.size() == 100
        deterministic, _ = model.predict(online.observations[:100, 0], deterministic=True)
        return online.actions[:100, 0] - model.policy.scale_action(deterministic)

    np.testing.assert_allclose(acted_minus_deterministic(deterministic_rollouts=True), 0.0, atol=1e-6)
    noise = NormalActionNoise(mean=np.zeros(1), sigma=np.full(1, 0.1))
    noisy = acted_minus_deterministic(deterministic_rollouts=True, action_noise=noise)
    assert 0.07 < noisy.std() < 0.13 and abs(noisy.mean()) < 0.03  # N(0, 0.1) around the deterministic action
    assert np.abs(acted_minus_deterministic()).mean() > 0.2  # SAC's samples of the untrained policy (std ~1)


def test_a_model_trained_offline_fine_tunes_after_load_with_an_online_fraction(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    dataset = collect_dataset(CollectionSpec(n_episodes=1, env_kwargs={"action_mode": "delta"}),
                              "sb3cql/Panda-v0/pid-delta-v0", progress_bar=False)  # fmt: skip
    env = gym.make("Panda-v0", action_mode="delta", max_episode_steps=40)
    CQL("MlpPolicy", env, dataset="sb3cql/Panda-v0/pid-delta-v0", batch_size=32, policy_kwargs=TINY).save(tmp_path / "m")
    force = gym.make("PandaForce-v0", action_mode="delta", max_episode_steps=40)
    model = CQL.load(tmp_path / "m", env=force, online_fraction=0.5, online_buffer_size=1_000)
    model.learn(50)  # the offline data come back from the dataset id
    assert (model.replay_buffer.offline.size(), model.replay_buffer.online.size()) == (dataset.total_steps, 50)
    assert model.replay_buffer.online.timeouts[39, 0] == 1.0  # the env's time limit is kept apart from terminations
    with pytest.raises(ValueError, match="spaces do not match"):
        CQL.load(tmp_path / "m", env=gym.make("PandaForce-v0"), online_fraction=0.5)  # absolute actions


def test_warm_start_imitates_saturated_data_actions():
    """During ``bc_steps`` the deterministic action follows the data's, also where they saturate at the bound (as the
    gripper's +-1): the entropy term, near 1 at the start, shapes only the spread."""
    env = OneStepBandit()
    buffer = ReplayBuffer(500, env.observation_space, env.action_space)
    for _ in range(500):
        buffer.add(np.zeros(1), np.zeros(1), np.array([1.0]), np.array([0.0]), np.array([True]), [{}])
    model = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, actor_learning_rate=1e-3, bc_steps=10_000,
                policy_kwargs=TINY, seed=0)  # fmt: skip
    model.learn(500)
    action, _ = model.predict(np.zeros(1, dtype=np.float32), deterministic=True)
    assert action[0] > 0.9


def test_warm_start_spread_losses_train_only_the_log_std_head(monkeypatch):
    """Without the least-squares term, the warm start's entropy term changes the log-std head and nothing the mean
    depends on."""
    monkeypatch.setattr("sb3_cql.cql.cql.behaviour_cloning_loss", lambda mean_actions, actions: 0.0 * mean_actions.sum())
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(200), batch_size=32, actor_learning_rate=1e-2,
                bc_steps=1000, policy_kwargs=TINY, seed=0)  # fmt: skip
    before = {name: value.clone() for name, value in model.actor.named_parameters()}
    model.learn(20)
    changed = {name for name, value in model.actor.named_parameters() if not th.equal(value, before[name])}
    assert changed == {"log_std.weight", "log_std.bias"}


def test_warm_start_learning_rate_decays_to_the_actors():
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(200), batch_size=32, actor_learning_rate=1e-4,
                bc_steps=100, bc_learning_rate=1e-2, policy_kwargs=TINY, seed=0)  # fmt: skip
    rates = []
    for _ in range(4):
        model.learn(50, reset_num_timesteps=False)
        rates.append(model.actor.optimizer.param_groups[0]["lr"])
    # set before the step that starts at num_timesteps 49 and 99, then the Q phase's rate
    np.testing.assert_allclose(rates, [1e-2 + 0.49 * (1e-4 - 1e-2), 1e-2 + 0.99 * (1e-4 - 1e-2), 1e-4, 1e-4], rtol=1e-6)


def test_warm_start_continues_where_a_saved_model_left_it(tmp_path):
    """RL-Zoo3 continues a checkpoint (``-i``) with ``learn`` counting timesteps from 0 again: the warm start still
    ends ``bc_steps`` gradient steps after the model's first."""
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(200), batch_size=32, actor_learning_rate=1e-4,
                bc_steps=100, bc_learning_rate=1e-2, policy_kwargs=TINY, seed=0)  # fmt: skip
    model.learn(60)
    model.save(tmp_path / "checkpoint.zip")
    model = CQL.load(tmp_path / "checkpoint.zip", env=gym.make("Pendulum-v1"), buffer_size=200)
    model.replay_buffer = random_pendulum_buffer(200)
    model.learn(30)  # reset_num_timesteps=True, as the zoo's
    assert model.num_timesteps == 30
    np.testing.assert_allclose(model.actor.optimizer.param_groups[0]["lr"], 1e-2 + 0.89 * (1e-4 - 1e-2), rtol=1e-6)
    model.learn(20)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)  # the Q phase after 110 steps


def test_actor_bc_weight_holds_the_actor_near_the_data_after_the_warm_start():
    """Data mostly at a = -0.8 with reward 1 - a^2, so Q is highest at a = 0 and imitation at about -0.64: without the
    anchor the actor follows Q; with a large ``actor_bc_weight`` it stays with the data."""
    env = OneStepBandit()
    rng = np.random.default_rng(0)
    actions = np.where(rng.random(2000) < 0.8, -0.8, rng.uniform(-1.0, 1.0, size=2000))
    buffer = ReplayBuffer(2000, env.observation_space, env.action_space)
    for action in actions:
        buffer.add(np.zeros(1), np.zeros(1), np.array([action]), np.array([1 - action**2]), np.array([True]), [{}])

    def trained_action(actor_bc_weight):
        model = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, learning_rate=1e-3, actor_learning_rate=1e-3,
                    cql_alpha=0.0, actor_bc_weight=actor_bc_weight, policy_kwargs=TINY, seed=0)  # fmt: skip
        model.learn(1500)
        return model.predict(np.zeros(1, dtype=np.float32), deterministic=True)[0][0]

    assert abs(trained_action(0.0)) < 0.2
    assert trained_action(50.0) == pytest.approx(actions.mean(), abs=0.1)


@pytest.mark.parametrize("options", [{"cql_n_actions": 0}, {"cql_temperature": 0.0}, {"cql_alpha": -1.0},
                                     {"actor_bc_weight": -1.0}, {"actor_bc_weight": float("nan")}])  # fmt: skip
def test_invalid_cql_settings_are_rejected(options):
    with pytest.raises(SettingError, match=next(iter(options))):
        CQL("MlpPolicy", "Pendulum-v1", **options)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"gamma": 1.5}, "gamma must be in (0, 1], got 1.5"),
        ({"gamma": -1}, "gamma must be in (0, 1], got -1"),
        ({"gamma": 0.0}, "gamma must be in (0, 1], got 0.0"),
        ({"tau": 2}, "tau must be in [0, 1], got 2"),
        ({"bc_steps": -3}, "bc_steps must be an integer >= 0, got -3"),
        ({"batch_size": 0}, "batch_size must be an integer >= 1, got 0"),
        ({"batch_size": -5}, "batch_size must be an integer >= 1, got -5"),
        ({"batch_size": 2.5}, "batch_size must be an integer >= 1, got 2.5"),
        ({"learning_starts": -1}, "learning_starts must be an integer >= 0, got -1"),
        ({"gradient_steps": -3}, "gradient_steps must be an integer >= 0, or -1 (as many as the env steps), got -3"),
        ({"train_freq": (0, "step")}, "train_freq must be an integer >= 1, got 0"),
        ({"target_update_interval": 0}, "target_update_interval must be an integer >= 1, got 0"),
        ({"n_steps": 0}, "n_steps must be an integer >= 1, got 0"),
        ({"online_buffer_size": 0}, "online_buffer_size must be an integer >= 1, got 0"),
        ({"cql_temperature": -1.0}, "cql_temperature must be a number > 0, got -1.0"),
        ({"bc_learning_rate": 0.0}, "bc_learning_rate must be a number > 0, got 0.0"),
    ],
)
def test_settings_sb3_would_train_with_are_refused_naming_the_keyword_and_value(options, message):
    with pytest.raises(SettingError, match=f"^{re.escape(message)}$"):
        CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(64), policy_kwargs=TINY, **options)


def test_settings_given_to_load_are_checked_and_sb3s_gradient_steps_minus_one_is_kept(tmp_path):
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(64), gradient_steps=-1, policy_kwargs=TINY)
    model.save(tmp_path / "cql")
    assert CQL.load(tmp_path / "cql", gradient_steps=-1).gradient_steps == -1
    with pytest.raises(SettingError, match=re.escape("gamma must be in (0, 1], got 1.5")):
        CQL.load(tmp_path / "cql", gamma=1.5)  # as the zoo's -i with --hyperparams gamma:1.5 fine-tunes


@pytest.mark.parametrize("algorithm", [CQL, BC])
@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("rewards", np.inf, "the replay buffer's rewards hold inf at index 7"),
        ("observations", np.nan, "the replay buffer's observations hold nan at index 7"),
        ("next_observations", -np.inf, "the replay buffer's next_observations hold -inf at index 7"),
        ("actions", np.nan, "the replay buffer's actions hold nan at index 7"),
    ],
)
def test_a_replay_buffer_with_a_non_finite_value_is_refused_naming_the_field_and_index(algorithm, field, value, message):
    buffer = random_pendulum_buffer(64)
    getattr(buffer, field)[7, 0] = value
    getattr(buffer, field)[9, 0] = value
    with pytest.raises(DatasetError, match=f"^dataset: {re.escape(message)}: every value must be finite$"):
        algorithm("MlpPolicy", "Pendulum-v1", dataset=buffer, policy_kwargs=TINY)


def test_saves_keep_sb3s_paths_and_leave_no_temporary_file(tmp_path):
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(64), batch_size=16, policy_kwargs=TINY)
    model.save(tmp_path / "new folder" / "model")  # SB3 adds .zip, and makes the folder
    model.save(str(tmp_path / "model.v2"))  # a suffix is kept
    model.save_replay_buffer(tmp_path / "buffer")  # .pkl
    file = io.BytesIO()
    model.save(file)  # a file object is written as SB3 writes it
    assert sorted(path.name for path in tmp_path.rglob("*")) == ["buffer.pkl", "model.v2", "model.zip", "new folder"]
    assert CQL.load(tmp_path / "new folder" / "model.zip").num_timesteps == 0 and CQL.load(io.BytesIO(file.getvalue()))
    assert load_from_pkl(tmp_path / "buffer.pkl").size() == 64


#: Saves a tiny CQL's model (``save``) or replay buffer (``save_replay_buffer``), ``sys.argv[1]``, to ``sys.argv[2]``:
#: with ``sys.argv[3] == "existing"`` whole first, then with the write of SB3's file cut short: half the file written,
#: the process waits (on stdin) to be killed.
CUT_SHORT_SAVE = """
import io, sys
import gymnasium as gym
import numpy as np
from stable_baselines3.common import base_class, off_policy_algorithm, save_util
from stable_baselines3.common.buffers import ReplayBuffer
from sb3_cql import CQL

method, path, before = sys.argv[1:]
env = gym.make("Pendulum-v1")
buffer = ReplayBuffer(64, env.observation_space, env.action_space)
for _ in range(64):
    observation = env.observation_space.sample()
    buffer.add(observation, observation, env.action_space.sample() / 2, np.zeros(1), np.zeros(1), [{}])
model = CQL("MlpPolicy", env, dataset=buffer, batch_size=16, policy_kwargs={"net_arch": [8]}, device="cpu")
if before == "existing":
    getattr(model, method)(path)
saving = {"save": (base_class, "save_to_zip_file", "zip"), "save_replay_buffer": (off_policy_algorithm, "save_to_pkl", "pkl")}
module, name, suffix = saving[method]
whole_save = getattr(module, name)

def cut_short(target, *args, **kwargs):
    whole = io.BytesIO()
    whole_save(whole, *args, **kwargs)
    with save_util.open_path(target, "w", suffix=suffix) as file:
        file.write(whole.getvalue()[: len(whole.getvalue()) // 2])
        file.flush()
    print("half written", flush=True)
    sys.stdin.read()

setattr(module, name, cut_short)
model.num_timesteps = 7
getattr(model, method)(path)
"""


@pytest.mark.parametrize("method", ["save", "save_replay_buffer"])
@pytest.mark.parametrize("before", ["absent", "existing"])
def test_a_save_killed_mid_write_leaves_the_previous_file_or_none(tmp_path, method, before):
    path = tmp_path / ("model.zip" if method == "save" else "buffer.pkl")
    child = subprocess.Popen([sys.executable, "-c", CUT_SHORT_SAVE, method, str(path), before], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert "half written\n" in iter(child.stdout.readline, ""), "the save never began"
    finally:
        child.kill()  # SIGKILL, mid-write
        child.wait()
    hidden = [entry for entry in tmp_path.iterdir() if entry.name.startswith(".")]
    assert [entry.stat().st_size > 0 for entry in hidden] == [True]  # the half-written file, under a name of its own
    assert sorted(entry.name for entry in tmp_path.iterdir() if not entry.name.startswith(".")) == (
        [] if before == "absent" else [path.name]
    )
    if before == "existing":  # the file saved before, whole
        if method == "save":
            assert CQL.load(path).num_timesteps == 0
        else:
            assert load_from_pkl(path).size() == 64


def test_critics_learn_the_scaled_and_shifted_reward():
    """With ``reward_scale`` and ``reward_bias`` the critics fit ``scale * r + bias`` (one-step episodes: Q is the
    reward), while the buffer keeps the data's rewards."""
    env = OneStepBandit()
    buffer = ReplayBuffer(1000, env.observation_space, env.action_space)
    for action in np.random.default_rng(0).uniform(-1.0, 1.0, size=1000):
        buffer.add(np.zeros(1), np.zeros(1), np.array([action]), np.array([1 - action**2]), np.array([True]), [{}])
    rewards = buffer.rewards.copy()
    model = CQL("MlpPolicy", env, dataset=buffer, batch_size=64, learning_rate=1e-3, cql_alpha=0.0, reward_scale=4.0,
                reward_bias=-2.0, policy_kwargs=TINY, seed=0)  # fmt: skip
    model.learn(1500)
    actions = th.linspace(-0.9, 0.9, 7).reshape(-1, 1)
    with th.no_grad():
        q_values = th.cat(model.critic(th.zeros(7, 1), actions), dim=1).mean(dim=1)
    np.testing.assert_allclose(q_values.numpy(), (4.0 * (1 - actions**2) - 2.0).flatten().numpy(), atol=0.25)
    np.testing.assert_array_equal(model.replay_buffer.rewards, rewards)


@pytest.mark.slow
def test_cql_learns_pendulum_from_a_good_policys_data():
    """SAC learns Pendulum-v1 online; 20,000 transitions of its policy (with Gaussian noise for coverage) are CQL's
    only data; CQL trained offline must approach the data's return."""
    from stable_baselines3.common.evaluation import evaluate_policy

    env = gym.make("Pendulum-v1")
    expert = SAC("MlpPolicy", env, policy_kwargs={"net_arch": [64, 64]}, learning_starts=1000, seed=0)
    expert.learn(12_000)
    buffer = ReplayBuffer(20_000, env.observation_space, env.action_space)
    rng = np.random.default_rng(0)
    observation, _ = env.reset(seed=100)
    returns, episode_return = [], 0.0
    for _ in range(20_000):
        action = np.clip(expert.predict(observation, deterministic=True)[0] + 0.3 * rng.standard_normal(1), -2.0, 2.0)
        next_observation, reward, terminated, truncated, _ = env.step(action)
        buffer.add(observation, next_observation, action / 2.0, np.array([reward]), np.array([terminated]),
                   [{"TimeLimit.truncated": truncated}])  # fmt: skip
        episode_return += reward
        observation = next_observation
        if terminated or truncated:
            returns.append(episode_return)
            episode_return, observation = 0.0, env.reset()[0]
    data_return = float(np.mean(returns))

    model = CQL("MlpPolicy", env, dataset=buffer, batch_size=256, learning_rate=3e-4, actor_learning_rate=1e-4,
                policy_kwargs={"net_arch": [64, 64]}, seed=0)  # fmt: skip
    model.learn(10_000)
    cql_return, _ = evaluate_policy(model, gym.make("Pendulum-v1"), n_eval_episodes=10)
    print(f"Pendulum-v1: data return {data_return:.0f}, CQL return {cql_return:.0f} over 10 episodes")
    assert data_return > -400  # the data come from a good policy
    assert cql_return > data_return - 150


def test_fused_relu_mlp_computes_what_the_sequential_computes():
    th.manual_seed(0)
    network = th.nn.Sequential(th.nn.Linear(7, 16), th.nn.ReLU(), th.nn.Linear(16, 16), th.nn.ReLU(), th.nn.Linear(16, 1))
    inputs = th.randn(300, 7, requires_grad=True)
    expected = network(inputs)
    expected_grads = th.autograd.grad(expected.square().sum(), [inputs, *network.parameters()])
    fused = relu_mlp(inputs, relu_mlp_parameters(network))
    grads = th.autograd.grad(fused.square().sum(), [inputs, *network.parameters()])
    th.testing.assert_close(fused, expected)
    for grad, expected_grad in zip(grads, expected_grads, strict=True):
        th.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-5)
    # With an input that needs no gradient (CQL's case) the parameters' gradients are the same.
    fused = relu_mlp(inputs.detach(), relu_mlp_parameters(network))
    grads = th.autograd.grad(fused.square().sum(), list(network.parameters()))
    for grad, expected_grad in zip(grads, expected_grads[1:], strict=True):
        th.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-5)


def test_fused_relu_mlp_calls_onednn_only_on_cpu_tensors(monkeypatch):
    """oneDNN's fused linear has no kernel for GPU tensors: any other device takes the plain products."""
    import sb3_cql.cql.fused_mlp as fused_mlp

    calls = []

    def onednn(x, *args):
        calls.append(x.device.type)
        if x.device.type != "cpu":
            raise RuntimeError(f"oneDNN's linear has no {x.device.type} kernel")
        return th.addmm(args[1], x, args[0].t()).relu() if args[2] == "relu" else th.addmm(args[1], x, args[0].t())

    monkeypatch.setattr(fused_mlp, "_ONEDNN_LINEAR", onednn)
    network = th.nn.Sequential(th.nn.Linear(7, 16), th.nn.ReLU(), th.nn.Linear(16, 1))
    on_cpu = relu_mlp(th.randn(5, 7), relu_mlp_parameters(network))
    assert calls == ["cpu", "cpu"]
    network = network.to("meta")  # a device without oneDNN, as a GPU is; the meta device checks shapes only
    on_meta = relu_mlp(th.randn(5, 7, device="meta"), relu_mlp_parameters(network))
    assert calls == ["cpu", "cpu"] and on_meta.shape == on_cpu.shape == (5, 1)


def test_other_critic_networks_use_the_module_itself():
    tanh = th.nn.Sequential(th.nn.Linear(3, 8), th.nn.Tanh(), th.nn.Linear(8, 1))
    assert relu_mlp_parameters(tanh) is None
    assert relu_mlp_parameters(th.nn.Sequential(th.nn.Linear(3, 1))) is not None  # no hidden layer
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(200), batch_size=32, seed=0,
                policy_kwargs={**TINY, "activation_fn": th.nn.Tanh})  # fmt: skip
    model.learn(5)
    assert model._n_updates == 5


def test_policy_actions_are_sampled_as_from_repeated_states():
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=random_pendulum_buffer(200), batch_size=32, policy_kwargs=TINY, seed=0)
    observations = th.randn(6, 3)
    th.manual_seed(1)
    with th.no_grad():
        actions, log_prob = model.sample_policy_actions(*model.actor.get_action_dist_params(observations)[:2], 4)
    th.manual_seed(1)
    expected_actions, expected_log_prob = model.actor.action_log_prob(observations.repeat_interleave(4, dim=0))
    th.testing.assert_close(actions, expected_actions)
    th.testing.assert_close(log_prob, expected_log_prob)


def test_freed_memory_is_retained_on_glibc():
    import platform

    assert retain_freed_memory() == (platform.libc_ver()[0] == "glibc")
