"""CQL's losses against the reference implementations': the critic loss of one batch as tinkoff-ai/CORL writes it, the
old halved-TD form against the reference form with twice the weight, and the imitation anchor's actor loss."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import Logger
from torch.distributions import Normal
from torch.nn import functional as F

from sb3_cql import CQL

TINY = {"net_arch": [32, 32]}
BATCH, N_ACTIONS = 32, 4


def pendulum_buffer(n_transitions: int = 1000, seed: int = 0) -> ReplayBuffer:
    """Random-action Pendulum-v1 transitions, actions scaled to [-1, 1], rewards scaled by 1/16 (small losses)."""
    env = gym.make("Pendulum-v1")
    env.action_space.seed(seed)
    buffer = ReplayBuffer(n_transitions, env.observation_space, env.action_space)
    observation, _ = env.reset(seed=seed)
    for _ in range(n_transitions):
        action = env.action_space.sample()
        next_observation, reward, terminated, truncated, _ = env.step(action)
        buffer.add(observation, next_observation, action / 2.0, np.array([reward / 16.0]), np.array([terminated]),
                   [{"TimeLimit.truncated": truncated}])  # fmt: skip
        observation = next_observation if not (terminated or truncated) else env.reset()[0]
    return buffer


class RecordingCQL(CQL):
    """CQL that keeps the critic loss of its last gradient step."""

    def check_critic_loss(self, critic_loss: th.Tensor) -> float:
        self.last_critic_loss = critic_loss.detach().clone()
        return super().check_critic_loss(critic_loss)


class HalvedTDCQL(RecordingCQL):
    """The loss before it followed the references: SAC's halved TD loss, ``0.5 * sum`` of the critics' MSE."""

    def td_loss(self, current_q_values, target_q_values):
        return 0.5 * super().td_loss(current_q_values, target_q_values)


def tanh_gaussian_sample(mean: th.Tensor, log_std: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """A tanh-squashed Gaussian sample and its log-density (SB3's, with its 1e-6 inside the log's correction)."""
    gaussian = Normal(mean, log_std.exp()).rsample()
    action = th.tanh(gaussian)
    log_prob = Normal(mean, log_std.exp()).log_prob(gaussian).sum(dim=1)
    return action, log_prob - th.log(1 - action**2 + 1e-6).sum(dim=1)


def corl_critic_loss(model: CQL, seed: int) -> float:
    """tinkoff-ai/CORL's ``ContinuousCQL._q_loss`` (deterministic backup, importance-sampled log-sum-exp, no clipping
    of the gap), written out on the model's own networks and one batch, with the random draws in the order
    ``CQL.train`` makes them: the batch, the actor's sample at s, the next-state backup's sample, then the uniform,
    current-policy and next-policy actions of the log-sum-exp."""
    np.random.seed(seed)
    th.manual_seed(seed)
    batch = model.replay_buffer.sample(BATCH)
    observations, actions, dimension = batch.observations, batch.actions, batch.actions.shape[1]
    with th.no_grad():
        mean, log_std, _ = model.actor.get_action_dist_params(observations)
        Normal(mean, log_std.exp()).rsample()  # the actor loss's sample, drawn first in training
        next_mean, next_log_std, _ = model.actor.get_action_dist_params(batch.next_observations)
        next_actions, _ = tanh_gaussian_sample(next_mean, next_log_std)
        target_q = th.min(*model.critic_target(batch.next_observations, next_actions))
        td_target = batch.rewards + (1.0 - batch.dones) * model.gamma * target_q
        q_predicted = model.critic(observations, actions)

        random_actions = th.empty(BATCH, N_ACTIONS, dimension).uniform_(-1, 1)
        repeat = N_ACTIONS
        current_actions, current_log_pis = tanh_gaussian_sample(
            mean.repeat_interleave(repeat, 0), log_std.repeat_interleave(repeat, 0)
        )
        cql_next_actions, cql_next_log_pis = tanh_gaussian_sample(
            next_mean.repeat_interleave(repeat, 0), next_log_std.repeat_interleave(repeat, 0)
        )
        repeated = observations.repeat_interleave(repeat, 0)
        q_random = model.critic(repeated, random_actions.reshape(-1, dimension))
        q_current = model.critic(repeated, current_actions)
        q_next = model.critic(repeated, cql_next_actions)

        random_density = np.log(0.5**dimension)
        loss = 0.0
        for critic in range(2):
            qf_loss = F.mse_loss(q_predicted[critic], td_target)
            cat_q = th.cat(
                [
                    q_random[critic].reshape(BATCH, repeat) - random_density,
                    q_next[critic].reshape(BATCH, repeat) - cql_next_log_pis.reshape(BATCH, repeat),
                    q_current[critic].reshape(BATCH, repeat) - current_log_pis.reshape(BATCH, repeat),
                ],
                dim=1,
            )
            cql_qf_ood = th.logsumexp(cat_q / model.cql_temperature, dim=1) * model.cql_temperature
            cql_qf_diff = (cql_qf_ood - q_predicted[critic].squeeze(1)).mean()
            if model.cql_target_action_gap is None:
                cql_min_qf_loss = cql_qf_diff * model.cql_alpha
            else:  # the multiplier before this step's dual update: log alpha' = 0 at the first step
                alpha_prime = th.clamp(th.exp(model.log_alpha_prime.detach()), min=0.0, max=1000000.0)
                cql_min_qf_loss = alpha_prime * model.cql_alpha * (cql_qf_diff - model.cql_target_action_gap)
            loss = loss + qf_loss + cql_min_qf_loss
    return float(loss)


@pytest.mark.parametrize("options", [{"cql_alpha": 10.0, "cql_target_action_gap": None}, {},
                                     {"cql_alpha": 3.0, "cql_target_action_gap": 2.0},
                                     {"cql_alpha": 5.0, "cql_temperature": 2.0, "cql_target_action_gap": None}])  # fmt: skip
def test_the_critic_loss_of_one_batch_is_corls(options):
    """Each critic's full MSE plus ``cql_alpha`` times its gap (with the Lagrange multiplier, ``alpha' * cql_alpha *
    (gap - target)``), summed over the critics: CORL's critic loss, to float32 rounding."""
    model = RecordingCQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(), batch_size=BATCH,
                         cql_n_actions=N_ACTIONS, policy_kwargs=TINY, seed=0, **options)  # fmt: skip
    model.set_logger(Logger(folder=None, output_formats=[]))
    model.learn(20)  # away from the initial parameters, targets apart from the critics
    expected = corl_critic_loss(model, seed=7)
    np.random.seed(7)
    th.manual_seed(7)
    model.train(gradient_steps=1, batch_size=BATCH)
    assert model.last_critic_loss.item() == pytest.approx(expected, rel=1e-6, abs=1e-6)


def test_the_conservative_loss_takes_the_multiplier_and_its_own_step_moves_it():
    """With ``cql_target_action_gap``, :meth:`conservative_loss` is ``alpha' * cql_alpha * (gap - target)`` summed over
    the critics and leaves ``alpha'`` as it is; :meth:`update_alpha_prime` makes the dual step, raising ``alpha'`` while
    the gaps exceed the target and lowering it below."""
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(200), cql_alpha=3.0, cql_target_action_gap=2.0,
                policy_kwargs=TINY, seed=0)  # fmt: skip
    model.log_alpha_prime.data.fill_(np.log(0.5))
    gaps = [th.tensor(5.0, requires_grad=True), th.tensor(4.0, requires_grad=True)]
    loss = model.conservative_loss(gaps)
    assert loss.item() == pytest.approx(0.5 * 3.0 * ((5.0 - 2.0) + (4.0 - 2.0)))
    assert model.log_alpha_prime.item() == pytest.approx(np.log(0.5))  # no step taken
    assert model.alpha_prime_optimizer.state_dict()["state"] == {}
    logs = {}
    model.update_alpha_prime(gaps, logs)
    assert model.log_alpha_prime.item() > np.log(0.5)
    assert logs["train/cql_alpha_prime"] == [pytest.approx(0.5)]  # before the step
    assert logs["train/cql_alpha_prime_loss"] == [pytest.approx(-0.5 * 0.5 * 3.0 * 5.0)]
    model.alpha_prime_optimizer.state.clear()  # Adam's first step, without the momentum of the one above
    before = model.log_alpha_prime.item()
    model.update_alpha_prime([th.tensor(1.0), th.tensor(0.0)], {})
    assert model.log_alpha_prime.item() < before
    loss.backward()
    assert [gap.grad.item() for gap in gaps] == pytest.approx([1.5, 1.5])  # alpha' * cql_alpha, alpha' detached
    plain = CQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(200), cql_alpha=3.0,
                cql_target_action_gap=None, policy_kwargs=TINY)  # fmt: skip
    assert plain.alpha_prime_optimizer is None and plain.conservative_loss(gaps).item() == pytest.approx(27.0)


def train_copy(model_class: type[CQL], cql_alpha: float, steps: int, buffer: ReplayBuffer) -> CQL:
    model = model_class("MlpPolicy", "Pendulum-v1", dataset=buffer, batch_size=BATCH, cql_alpha=cql_alpha,
                        cql_n_actions=N_ACTIONS, policy_kwargs=TINY, seed=0)  # fmt: skip
    model.learn(steps)
    return model


def critic_difference(first: CQL, second: CQL) -> float:
    """The largest absolute difference between the two models' critic parameters."""
    pairs = zip(first.critic.parameters(), second.critic.parameters(), strict=True)
    return max((a - b).abs().max().item() for a, b in pairs)


def test_the_halved_td_loss_at_weight_a_trains_as_the_full_one_at_2a():
    """``0.5 * TD + a * gap`` is half of ``TD + 2a * gap``: Adam's steps do not see a loss's scale (up to its eps), so
    from the same seed on the same data the two train the same networks, where ``TD + a * gap`` does not. (Doubling
    is exact in floating point, so the gradients are exactly twice the old ones and only Adam's eps tells them
    apart.)"""
    steps = 100
    buffer = pendulum_buffer()  # offline training leaves it as it is
    halved = train_copy(HalvedTDCQL, cql_alpha=5.0, steps=steps, buffer=buffer)
    doubled = train_copy(RecordingCQL, cql_alpha=10.0, steps=steps, buffer=buffer)
    same_alpha = train_copy(RecordingCQL, cql_alpha=5.0, steps=steps, buffer=buffer)
    assert doubled.last_critic_loss.item() == pytest.approx(2 * halved.last_critic_loss.item(), rel=1e-3)
    equivalent, different = critic_difference(halved, doubled), critic_difference(halved, same_alpha)
    largest = max(p.abs().max().item() for p in halved.critic.parameters())
    print(f"after {steps} steps: largest critic parameter {largest:.3g}, |halved(5) - full(10)| {equivalent:.3g}, "
          f"|halved(5) - full(5)| {different:.3g}")  # fmt: skip
    assert equivalent < 1e-2 * different


def test_the_anchor_divides_sacs_whole_actor_loss_by_mean_abs_q():
    """``actor_bc_weight``: ``mean(ent_coef * log_prob - Q) / mean(|Q|) + weight * bc``: the entropy term is divided
    with the Q term (the documentation says why), and the imitation is added at its weight."""
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(200), actor_bc_weight=2.0, policy_kwargs=TINY, seed=0)
    log_prob = th.tensor([[-1.0], [0.5], [2.0]], requires_grad=True)
    min_qf_pi = th.tensor([[-300.0], [-200.0], [100.0]], requires_grad=True)
    ent_coef = th.tensor(0.3)
    mean_actions = th.tensor([[0.2], [-0.1], [0.4]], requires_grad=True)
    replay_data = model.replay_buffer.sample(3)
    actor_loss = (ent_coef * log_prob - min_qf_pi).mean()
    logs = {}
    loss = model.anchor_actor_loss(actor_loss, min_qf_pi, mean_actions, replay_data, logs=logs)
    bc = F.mse_loss(th.tanh(mean_actions), replay_data.actions)
    assert loss.item() == pytest.approx((actor_loss / 200.0 + 2.0 * bc).item(), rel=1e-6)
    assert logs["train/actor_bc_loss"] == [pytest.approx(bc.item())]
    loss.backward()
    assert log_prob.grad.flatten().tolist() == pytest.approx([0.1 / 200.0] * 3)  # ent_coef / batch / mean |Q|
    assert min_qf_pi.grad.flatten().tolist() == pytest.approx([-1 / 600.0] * 3)
    model.actor_bc_weight = 0.0
    assert model.anchor_actor_loss(actor_loss, min_qf_pi, mean_actions, replay_data, logs={}) is actor_loss


@pytest.mark.parametrize(("options", "step"), [({}, 1e-4), ({"cql_alpha_learning_rate": None}, 3e-4),
                                               ({"learning_rate": 1e-3, "cql_alpha_learning_rate": 2e-5}, 2e-5),
                                               ({"learning_rate": 1e-3, "cql_alpha_learning_rate": None}, 1e-3)])  # fmt: skip
def test_the_multipliers_learning_rate_is_its_own_keyword_or_the_critics(options, step, tmp_path):
    """Adam's first step moves ``log(alpha')`` by its learning rate: ``cql_alpha_learning_rate`` (1e-4 by default;
    kept through ``train``, whose schedule update sets the other optimizers), or ``learning_rate`` where it is
    ``None``; a loaded model keeps it."""
    model = CQL("MlpPolicy", "Pendulum-v1", dataset=pendulum_buffer(200), batch_size=BATCH, policy_kwargs=TINY, seed=0,
                **options)  # fmt: skip
    model.set_logger(Logger(None, []))
    model.train(gradient_steps=1, batch_size=BATCH)
    assert abs(model.log_alpha_prime.item()) == pytest.approx(step, rel=1e-3)
    model.save(tmp_path / "cql")
    loaded = CQL.load(tmp_path / "cql")
    loaded.replay_buffer = model.replay_buffer
    before = loaded.log_alpha_prime.item()
    loaded.alpha_prime_optimizer.state.clear()
    loaded.set_logger(Logger(None, []))
    loaded.train(gradient_steps=1, batch_size=BATCH)
    assert abs(loaded.log_alpha_prime.item() - before) == pytest.approx(step, rel=1e-3)
