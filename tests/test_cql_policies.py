"""CQL's policy classes: SAC's networks with the fused critic pass and the warm start's distribution parameters, each
checked against the SB3 method it follows (a change of SB3 underneath fails here)."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from rollouts import random_rollouts
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.sac.policies import SACPolicy

import sb3_cql.cql.policies as cql_policies
from sb3_cql import CQL
from sb3_cql.cql.policies import CQLActor, CQLCritic, CQLPolicy

TINY = {"net_arch": [32, 32]}


def pendulum_buffer(n_transitions: int = 300) -> ReplayBuffer:
    return random_rollouts(gym.make("Pendulum-v1"), n_transitions)


def policy(share_features_extractor: bool) -> CQLPolicy:
    env = gym.make("Pendulum-v1")
    th.manual_seed(0)
    return CQLPolicy(env.observation_space, env.action_space, lambda _: 1e-3, net_arch=[16, 16],
                     share_features_extractor=share_features_extractor)  # fmt: skip


@pytest.mark.parametrize("share_features_extractor", [False, True])
def test_the_fused_critic_pass_computes_sb3s_forward_with_its_gradients(share_features_extractor):
    critic = policy(share_features_extractor).critic
    assert isinstance(critic, CQLCritic)
    observations, actions = th.randn(50, 3), th.rand(50, 1) * 2 - 1
    expected = critic(observations, actions)
    expected_grads = th.autograd.grad(sum(q.square().sum() for q in expected), list(critic.parameters()), allow_unused=True)
    fused = critic.forward_fused(observations, actions)
    grads = th.autograd.grad(sum(q.square().sum() for q in fused), list(critic.parameters()), allow_unused=True)
    assert len(fused) == len(expected) == 2
    for q, expected_q in zip(fused, expected, strict=True):
        th.testing.assert_close(q, expected_q)
    for grad, expected_grad in zip(grads, expected_grads, strict=True):
        assert (grad is None) == (expected_grad is None)  # e.g. a shared features extractor gets none from the critic
        if grad is not None:
            th.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-5)


def test_the_fused_critic_pass_is_sb3s_forward_off_the_cpu(monkeypatch):
    critic = policy(False).critic.to("meta")  # a device without oneDNN, as a GPU is; the meta device checks shapes

    def no_fusion(*args):
        raise AssertionError("the fused pass ran on a tensor off the CPU")

    monkeypatch.setattr(cql_policies, "relu_mlp", no_fusion)
    q_values = critic.forward_fused(th.randn(5, 3, device="meta"), th.randn(5, 1, device="meta"))
    assert [q.shape for q in q_values] == [(5, 1), (5, 1)]


def test_the_warm_starts_distribution_is_sacs_with_the_log_std_learning_in_its_head_only():
    actor = policy(False).actor
    assert isinstance(actor, CQLActor)
    observations = th.randn(20, 3)
    mean_actions, log_std, _ = actor.get_action_dist_params(observations)
    imitation_mean, imitation_log_std = actor.imitation_dist_params(observations)
    th.testing.assert_close(imitation_mean, mean_actions)
    th.testing.assert_close(imitation_log_std, log_std)
    imitation_log_std.sum().backward()
    assert all(parameter.grad is None for parameter in actor.latent_pi.parameters())
    assert all(parameter.grad is not None for parameter in actor.log_std.parameters())


def test_a_model_saved_with_sacs_policy_class_loads_into_cqls(tmp_path):
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(), batch_size=32, policy_kwargs=TINY, seed=0)
    assert isinstance(model.policy, CQLPolicy)
    model.policy_class = SACPolicy  # as saved before CQL had policy classes of its own
    model.save(tmp_path / "model.zip")
    loaded = CQL.load(tmp_path / "model.zip", env=gym.make("Pendulum-v1"))
    assert type(loaded.policy) is CQLPolicy and isinstance(loaded.critic, CQLCritic)
    observations = np.random.default_rng(0).standard_normal((4, 3)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(observations, deterministic=True)[0],
                                  model.predict(observations, deterministic=True)[0])  # fmt: skip
    loaded.replay_buffer = pendulum_buffer()
    loaded.learn(3)
    assert loaded._n_updates == 3


def test_a_policy_of_sacs_own_classes_trains_with_cqls_passes():
    """A policy class of the user's built on SAC's (its actor and critic SAC's own) gets the same warm start and
    conservative term."""

    class UsersPolicy(SACPolicy):
        pass

    model = CQL(UsersPolicy, "Pendulum-v1", dataset=pendulum_buffer(), batch_size=32, bc_steps=3, seed=0,
                normalize_observations=False, policy_kwargs=TINY)  # fmt: skip
    assert type(model.critic).__name__ == "ContinuousCritic"
    model.learn(6)  # 3 warm-start steps, 3 steps following Q
    assert model._n_updates == 6


def test_a_critic_with_a_forward_of_its_own_keeps_it_in_the_conservative_term():
    critic = policy(False).critic
    calls = []

    class OwnForward(CQLCritic):
        def forward(self, obs, actions):
            calls.append(len(obs))
            return super().forward(obs, actions)

    critic.__class__ = OwnForward
    critic.forward_fused(th.randn(5, 3), th.randn(5, 1))
    assert calls == [5]


def test_critic_layer_norm_normalises_each_hidden_layer_and_saves_with_the_model(tmp_path):
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(), batch_size=32, seed=0,
                policy_kwargs={**TINY, "critic_layer_norm": True})  # fmt: skip
    for critic in (model.critic, model.critic_target):
        layers = [type(layer).__name__ for layer in critic.q_networks[0]]
        assert layers == ["Linear", "LayerNorm", "ReLU", "Linear", "LayerNorm", "ReLU", "Linear"]
        assert critic.qf0 is critic.q_networks[0]
    assert all(type(layer).__name__ != "LayerNorm" for layer in model.actor.latent_pi)
    model.learn(5)  # the conservative term takes SB3's forward: no fused pass for these networks
    model.save(tmp_path / "model.zip")
    loaded = CQL.load(tmp_path / "model.zip")
    for name, parameter in model.critic.state_dict().items():
        assert th.equal(parameter, loaded.critic.state_dict()[name]), name
