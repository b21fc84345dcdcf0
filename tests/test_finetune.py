"""Online fine-tuning of an offline IQL model: IQL's own losses on batches mixed from the offline data and the new
episodes, with the random-yaw recipe's settings (n-step returns, the averaged actor, the DDPG+AWR actor), saved and
loaded mid-way with its online transitions."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from rollouts import random_rollouts
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.logger import configure

from sb3_cql import IQL
from sb3_cql.common import MixedReplayBuffer

TINY = {"net_arch": [16]}
#: The random-yaw recipe's IQL settings (hyperparams/iql_yaw.yml), at a tiny scale.
RECIPE = {"gamma": 0.999, "expectile": 0.5, "temperature": 50.0, "actor_loss_type": "ddpg_awr", "actor_bc_weight": 4.0,
          "q_agg": "mean", "target_floor": 0.0, "actor_average_tau": 0.001, "n_steps": 5}  # fmt: skip


def pendulum_buffer(n_transitions: int = 400) -> ReplayBuffer:
    return random_rollouts(gym.make("Pendulum-v1"), n_transitions)


def test_iql_fine_tunes_with_its_own_losses_on_mixed_batches_and_continues_from_a_saved_buffer(tmp_path):
    offline, env = pendulum_buffer(), gym.make("Pendulum-v1")  # episodes of 200 steps
    model = IQL("MlpPolicy", env, dataset=offline, batch_size=32, policy_kwargs=TINY, seed=0, **RECIPE).learn(50)
    model.save(tmp_path / "offline")

    tuned = IQL.load(tmp_path / "offline", env=env, online_fraction=0.5, online_buffer_size=2_000, seed=1)
    tuned.replay_buffer = offline  # the dataset of a model trained on a buffer (an id would be reloaded)
    tuned.set_logger(configure(str(tmp_path / "logs"), ["csv"]))
    before = offline.observations.copy()
    tuned.learn(300, log_interval=1)
    buffer = tuned.replay_buffer
    assert isinstance(buffer, MixedReplayBuffer) and isinstance(buffer.online, NStepReplayBuffer)
    assert buffer.online.n_steps == buffer.offline.n_steps == 5
    assert tuned.num_timesteps == 300 and tuned._n_updates == 50 + 300  # one gradient step per env step
    assert (buffer.offline.size(), buffer.online.size()) == (400, 300)
    np.testing.assert_array_equal(buffer.offline.observations, before)
    samples = buffer.sample(64)
    assert samples.discounts is not None  # n-step returns from both parts
    # The policy acted with the averaged actor, which moved towards the trained actor.
    actor, average = tuned.policy.actor, tuned.policy.actor_average
    assert not all(th.equal(a, b) for a, b in zip(actor.parameters(), average.parameters(), strict=True))

    tuned.save(tmp_path / "tuned")
    tuned.save_replay_buffer(tmp_path / "tuned_buffer")
    loaded = IQL.load(tmp_path / "tuned", env=env)
    observations = np.stack([env.observation_space.sample() for _ in range(8)])
    np.testing.assert_array_equal(loaded.predict(observations, deterministic=True)[0],
                                  tuned.predict(observations, deterministic=True)[0])  # fmt: skip
    assert loaded.online_fraction == 0.5 and loaded.actor_loss_type == "ddpg_awr" and loaded.n_steps == 5
    loaded.load_replay_buffer(tmp_path / "tuned_buffer")
    assert loaded.replay_buffer.online.size() == 300  # the online transitions are kept
    loaded.replay_buffer.set_offline(buffer.offline)  # the offline data as the model reads them
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_timesteps == 400 and loaded.replay_buffer.online.size() == 400


@pytest.mark.parametrize("online_fraction", [0.0, 1.0])
def test_the_online_fraction_decides_where_each_batch_comes_from(online_fraction):
    offline = pendulum_buffer()
    model = IQL("MlpPolicy", "Pendulum-v1", dataset=offline, batch_size=32, policy_kwargs=TINY, seed=5,
                online_fraction=online_fraction, online_buffer_size=1_000, gradient_steps=0)  # fmt: skip
    model.learn(250)  # an episode and a half, no gradient step
    buffer = model.replay_buffer
    sampled = buffer.sample(200).observations.numpy()
    from_offline = np.isin(sampled[:, 0], offline.observations[:400, 0, 0])
    assert from_offline.all() if online_fraction == 0.0 else not from_offline.any()


def test_the_warm_up_before_learning_starts_acts_with_the_models_policy_not_at_random():
    """WSRL's warm-up: the first ``learning_starts`` env steps are the offline model's own rollouts (here its
    deterministic action), with no gradient step; SAC would act uniformly at random."""
    offline = pendulum_buffer()
    model = IQL("MlpPolicy", "Pendulum-v1", dataset=offline, batch_size=32, policy_kwargs=TINY, seed=5,
                online_fraction=1.0, online_buffer_size=1_000, learning_starts=150, deterministic_rollouts=True)  # fmt: skip
    model.learn(150)
    online = model.replay_buffer.online
    assert online.size() == 150 and model._n_updates == 0
    deterministic, _ = model.predict(online.observations[:150, 0], deterministic=True)
    np.testing.assert_allclose(online.actions[:150, 0], model.policy.scale_action(deterministic), atol=1e-6)
    model.learn(10, reset_num_timesteps=False)
    assert model._n_updates == 10  # then one gradient step per env step, from the online transitions only


def test_a_loaded_model_warns_when_its_dataset_id_holds_other_transitions_than_it_was_trained_on(tmp_path, monkeypatch):
    """The same dataset id collected on two machines can hold different arrays: a model keeps the digest of the
    transitions it was trained on, and refilling its buffer from the id elsewhere says so, on one line, where they
    differ; on the same data it says nothing."""
    from sb3_cql.data import CollectionSpec, collect_dataset, transitions_digest

    here, there = tmp_path / "here", tmp_path / "there"
    for root, episodes in ((here, 1), (there, 2)):
        monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
        collect_dataset(CollectionSpec(n_episodes=episodes), progress_bar=False)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(here))
    model = IQL("MlpPolicy", "Panda-v0", dataset="sb3cql/Panda-v0/pid-v0", batch_size=32, policy_kwargs=TINY, seed=0)
    assert model.data_sha256 == transitions_digest(model.replay_buffer)
    model.save(tmp_path / "model")

    same = IQL.load(tmp_path / "model", env=gym.make("Panda-v0"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert same.load_offline_data().size() == model.replay_buffer.size()
    assert not [warning for warning in caught if "trained on" in str(warning.message)]
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(there))
    elsewhere = IQL.load(tmp_path / "model", env=gym.make("Panda-v0"))
    with pytest.warns(UserWarning, match=r"sb3cql/Panda-v0/pid-v0 \(transitions sha256 \w{12}\) are not those this model "
                                         rf"was trained on \({model.data_sha256[:12]}\)") as caught:  # fmt: skip
        assert elsewhere.load_offline_data().size() > model.replay_buffer.size()
    assert len(caught) == 1 and "\n" not in str(caught[0].message)
    assert elsewhere.data_sha256 == model.data_sha256  # it still names the data it was first trained on
