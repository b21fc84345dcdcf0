"""SB3's contracts for its algorithms, as its own generic tests check them (save/load, predict, run, determinism,
callbacks, Dict observations, images, n-step returns), with CQL, fine-tuning CQL, BC and IQL in SAC's place."""

import copy
import inspect

import gymnasium as gym
import minari
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from rollouts import random_rollouts
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.envs import FakeImageEnv, SimpleMultiObsEnv

from sb3_cql import BC, CQL, IQL, CalQL
from sb3_cql.common import MixedReplayBuffer, ReturnToGoReplayBuffer
from sb3_cql.common.policies import NormalizedFlatten

TINY = {"net_arch": [16]}
#: The algorithms under test: (class, keywords).
ALGORITHMS = {
    "cql": (CQL, {"cql_n_actions": 2}),
    "cql-finetune": (CQL, {"cql_n_actions": 2, "online_fraction": 0.5, "online_buffer_size": 1000}),
    "bc": (BC, {}),
    "iql": (IQL, {}),
    "iql-best-of-n": (IQL, {"best_of_n": 4}),
}


class MatrixObservationEnv(gym.Env):
    """Box observations of shape (2, 3), Box actions of 2: a task whose observations are not flat."""

    observation_space = spaces.Box(-1.0, 1.0, (2, 3), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.steps = 0
        return self.observation_space.sample(), {}

    def step(self, action):
        self.steps += 1
        return self.observation_space.sample(), float(action[0]), False, self.steps >= 20, {}


ENVS = {
    "pendulum": lambda: gym.make("Pendulum-v1"),
    "matrix": MatrixObservationEnv,
    "image-channel-last": lambda: FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=False),
    "image-channel-first": lambda: FakeImageEnv(40, 40, n_channels=2, discrete=False, channel_first=True),
    "dict": lambda: SimpleMultiObsEnv(random_start=True, discrete_actions=False),
}
POLICIES = {"pendulum": "MlpPolicy", "matrix": "MlpPolicy", "dict": "MultiInputPolicy"}


def policy_of(env_name: str) -> tuple[str, dict]:
    """The policy for the env, with small networks (and small image features)."""
    policy = POLICIES.get(env_name, "CnnPolicy")
    features = {"CnnPolicy": {"features_dim": 16}, "MultiInputPolicy": {"cnn_output_dim": 16}}.get(policy)
    return policy, TINY if features is None else {**TINY, "features_extractor_kwargs": features}


def make(algorithm: str, env_name: str, seed: int = 0, **kwargs):
    algorithm_class, keywords = ALGORITHMS[algorithm]
    policy, policy_kwargs = policy_of(env_name)
    return algorithm_class(policy, ENVS[env_name](), dataset=random_rollouts(ENVS[env_name](), 120), batch_size=8,
                           policy_kwargs=policy_kwargs, seed=seed, **{**keywords, **kwargs})  # fmt: skip


def observations_of(model, n: int):
    """``n`` observations of the model's env as the env gives them (channel-last images stay so)."""
    env = model.get_env()
    samples = [env.observation_space.sample() for _ in range(n)]
    if isinstance(samples[0], dict):
        return {key: np.stack([sample[key] for sample in samples]) for key in samples[0]}
    return np.stack(samples)


#: Each algorithm on each env, best-of-N acting on the flat and Dict observations only (the image envs add nothing to it).
PAIRS = [(algorithm, env_name) for algorithm in ALGORITHMS for env_name in ENVS
         if not (algorithm == "iql-best-of-n" and env_name.startswith("image"))]  # fmt: skip


@pytest.mark.parametrize(("algorithm", "env_name"), PAIRS)
def test_learn_predict_save_load_and_continue(algorithm, env_name, tmp_path):
    model = make(algorithm, env_name)
    model.learn(30)
    assert model.num_timesteps == 30
    observations = observations_of(model, 3)
    actions, _ = model.predict(observations, deterministic=True)
    assert actions.shape == (3, *model.action_space.shape) and model.action_space.contains(actions[0])
    single = {key: value[0] for key, value in observations.items()} if isinstance(observations, dict) else observations[0]
    assert model.predict(single, deterministic=True)[0].shape == model.action_space.shape
    model.save(tmp_path / "model.zip")
    loaded = type(model).load(tmp_path / "model.zip", env=ENVS[env_name]())
    np.testing.assert_allclose(loaded.predict(observations, deterministic=True)[0], actions, rtol=1e-6)
    # Parameters round trip, as SB3's get_parameters / set_parameters.
    other = make(algorithm, env_name, seed=1)
    other.set_parameters(model.get_parameters())
    np.testing.assert_allclose(other.predict(observations, deterministic=True)[0], actions, rtol=1e-6)
    # The saved replay buffer comes back and training continues its count.
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    size = model.replay_buffer.size()
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert model.replay_buffer.size() == size
    model.learn(10, reset_num_timesteps=False)
    assert model.num_timesteps == 40


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_the_same_seed_trains_the_same_model(algorithm):
    first = make(algorithm, "pendulum", seed=3).learn(25)
    second = make(algorithm, "pendulum", seed=3).learn(25)
    for (name, parameter), (_, other) in zip(first.policy.state_dict().items(), second.policy.state_dict().items(),
                                             strict=True):  # fmt: skip
        assert th.equal(parameter, other), name


class CountingCallback(BaseCallback):
    def __init__(self) -> None:
        super().__init__()
        self.starts = self.steps = self.ends = 0

    def _on_training_start(self) -> None:
        self.starts += 1

    def _on_step(self) -> bool:
        self.steps += 1
        return self.steps < 15  # stops training, as SB3's callbacks may

    def _on_training_end(self) -> None:
        self.ends += 1


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_callbacks_are_called_once_a_timestep_and_can_stop_training(algorithm):
    model, callback = make(algorithm, "pendulum"), CountingCallback()
    model.learn(40, callback=callback)
    assert (callback.starts, callback.steps, callback.ends) == (1, 15, 1)
    assert model.num_timesteps == 15
    model.predict(observations_of(model, 2))
    assert not model.policy.training  # predict puts the policy in evaluation mode, as SB3's


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_n_step_returns_train_save_and_load(algorithm, tmp_path):
    model = make(algorithm, "pendulum", n_steps=3)
    buffer = model.replay_buffer.offline if isinstance(model.replay_buffer, MixedReplayBuffer) else model.replay_buffer
    assert isinstance(buffer, NStepReplayBuffer) and buffer.n_steps == 3
    model.learn(20)
    model.save(tmp_path / "model.zip")
    assert type(model).load(tmp_path / "model.zip").n_steps == 3


@pytest.mark.parametrize(
    "options, buffer_class",
    [({}, ReplayBuffer), ({"n_steps": 3}, NStepReplayBuffer), ({"calibrated": True}, ReturnToGoReplayBuffer),
     ({"online_fraction": 0.5}, MixedReplayBuffer), ({"online_fraction": 0.5, "calibrated": True, "n_steps": 2},
     MixedReplayBuffer)],
)  # fmt: skip
def test_every_replay_buffer_we_make_saves_loads_and_copies_whole(options, buffer_class, tmp_path):
    options = dict(options)
    algorithm = CalQL if options.pop("calibrated", False) else CQL
    model = algorithm("MlpPolicy", "Pendulum-v1", dataset=random_rollouts(gym.make("Pendulum-v1"), 300), batch_size=16,
                      policy_kwargs=TINY, seed=0, **options)  # fmt: skip
    model.learn(20)
    assert type(model.replay_buffer) is buffer_class
    size = model.replay_buffer.size()
    assert copy.deepcopy(model.replay_buffer).size() == size
    model.save_replay_buffer(tmp_path / "buffer")
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert type(model.replay_buffer) is buffer_class and model.replay_buffer.size() == size
    model.learn(10, reset_num_timesteps=False)  # the offline part of a fine-tuning buffer stays under the loaded one
    assert model.num_timesteps == 30


@pytest.mark.parametrize("algorithm", ["cql", "bc", "iql"])
@pytest.mark.parametrize("env_name", ["image-channel-last", "dict"])
def test_a_minari_dataset_of_images_or_dict_observations_trains(algorithm, env_name, tmp_path, monkeypatch):
    """A Minari dataset in the env's own layout (channel-last images, Dict observations) loads as SB3 gives the
    observations to the policy (images channel-first)."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    env = ENVS[env_name]()
    env.action_space.seed(0)
    episodes = []
    for episode in range(3):
        observations, actions, rewards = [env.reset(seed=episode)[0]], [], []
        for _ in range(12):
            actions.append(env.action_space.sample())
            observation, reward, _, _, _ = env.step(actions[-1])
            observations.append(observation)
            rewards.append(reward)
        if isinstance(observations[0], dict):
            observations = {key: np.stack([o[key] for o in observations]) for key in observations[0]}
        else:
            observations = np.stack(observations)
        episodes.append(minari.data_collector.EpisodeBuffer(
            observations=observations, actions=np.stack(actions), rewards=np.array(rewards),
            terminations=np.zeros(12, bool), truncations=np.eye(12, dtype=bool)[-1],
        ))  # fmt: skip
    dataset = minari.create_dataset_from_buffers("test/contracts-v0", episodes, env=env, algorithm_name="t", author="t",
                                                 author_email="t", code_permalink="t", description="t",
                                                 jpeg_encoding=False)  # fmt: skip
    algorithm_class, keywords = ALGORITHMS[algorithm]
    policy, policy_kwargs = policy_of(env_name)
    model = algorithm_class(policy, ENVS[env_name](), dataset=dataset, batch_size=8, seed=0, policy_kwargs=policy_kwargs,
                            **keywords)  # fmt: skip
    assert model.replay_buffer.size() == 36
    first = dataset.iterate_episodes([0]).__next__().observations
    stored = model.replay_buffer.observations
    if env_name == "dict":
        np.testing.assert_array_equal(stored["vec"][0, 0], first["vec"][0])
        np.testing.assert_array_equal(stored["img"][0, 0], np.transpose(first["img"][0], (2, 0, 1)))
    else:
        np.testing.assert_array_equal(stored[0, 0], np.transpose(first[0], (2, 0, 1)))
    model.learn(5)
    assert model.num_timesteps == 5


def test_every_sac_keyword_is_cqls_with_sacs_default_or_refused_in_one_line():
    sac = inspect.signature(SAC.__init__).parameters
    assert set(sac) - {"self"} <= CQL.known_keywords()

    def default(algorithm: type, name: str) -> object:  # the default of the first class up the MRO that names it
        for klass in algorithm.__mro__:
            parameters = inspect.signature(klass.__dict__.get("__init__", object.__init__)).parameters
            if name in parameters:
                return parameters[name].default
        raise AssertionError(name)

    kept_other_defaults = {"learning_rate", "buffer_size", "batch_size", "learning_starts", "actor_learning_rate"}
    for name, parameter in sac.items():
        if name not in {"self", "policy", "env"} | kept_other_defaults:
            assert default(CQL, name) == parameter.default, name
    buffer = random_rollouts(gym.make("Pendulum-v1"), 50)
    for keyword, value in (("use_sde", True), ("use_sde_at_warmup", True), ("optimize_memory_usage", True)):
        with pytest.raises(ValueError, match=f"^{keyword}=True is not supported: "):
            CQL("MlpPolicy", "Pendulum-v1", dataset=buffer, **{keyword: value})
    with pytest.raises(TypeError, match="BC does not take gamma, tau: BC trains its actor"):
        BC("MlpPolicy", "Pendulum-v1", dataset=buffer, gamma=0.9, tau=0.1)
    with pytest.raises(TypeError, match="unexpected keyword arguments: colour"):
        BC("MlpPolicy", "Pendulum-v1", dataset=buffer, colour=1)


def test_normalize_observations_applies_to_an_mlp_policy_or_is_refused():
    buffer = random_rollouts(gym.make("Pendulum-v1"), 50)
    assert CQL("MlpPolicy", "Pendulum-v1", dataset=buffer).normalize_observations is True
    images = FakeImageEnv(40, 40, n_channels=2, discrete=False)
    model = CQL(
        "CnnPolicy", images, dataset=random_rollouts(FakeImageEnv(40, 40, n_channels=2, discrete=False), 20), batch_size=4
    )
    assert model.normalize_observations is False
    with pytest.raises(ValueError, match="normalize_observations=True z-scores flat Box observations of an MlpPolicy"):
        CQL("CnnPolicy", images, dataset=buffer, normalize_observations=True)


def test_iql_reads_raw_observations_by_default_as_the_references_and_z_scores_them_when_asked():
    buffer = random_rollouts(gym.make("Pendulum-v1"), 50)
    raw = IQL("MlpPolicy", "Pendulum-v1", dataset=buffer, seed=0)
    assert raw.normalize_observations is False
    assert not isinstance(raw.actor.features_extractor, NormalizedFlatten)
    observation = np.array([0.5, -0.5, 7.0], dtype=np.float32)
    assert np.allclose(raw.actor.features_extractor(th.as_tensor(observation)[None]).numpy(), observation)
    normalized = IQL("MlpPolicy", "Pendulum-v1", dataset=buffer, seed=0, normalize_observations=None)
    assert normalized.normalize_observations is True
    assert isinstance(normalized.actor.features_extractor, NormalizedFlatten)
    assert not np.allclose(normalized.actor.features_extractor(th.as_tensor(observation)[None]).numpy(), observation)
