"""IQL's update against a hand computation, best-of-N acting, long discounts, and filtered imitation."""

import copy
import re

import gymnasium as gym
import minari
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from rollouts import random_rollouts, spaces_env
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql import BC, CQL, IQL, CalQL
from sb3_cql.common import KeywordError, SettingError, TrainingDivergedError, returns_to_go
from sb3_cql.iql import expectile_loss
from sb3_cql.iql.policies import LOG_STD_MAX, LOG_STD_MIN, IQLActor

TINY = {"net_arch": [16]}


def pendulum_iql(algorithm: type[IQL] = IQL, **kwargs) -> IQL:
    env = gym.make("Pendulum-v1")
    settings = {"batch_size": 16, "seed": 0, "policy_kwargs": TINY, **kwargs}
    return algorithm("MlpPolicy", env, dataset=random_rollouts(gym.make("Pendulum-v1"), 300), **settings)


def one_recorded_update(model: IQL, batch_size: int):
    """One gradient step of ``model``: the policy as it was before it, the batch it drew and what it logged."""
    model._setup_learn(1, None)  # the logger
    before = copy.deepcopy(model.policy)
    state = np.random.get_state()
    batch = model.replay_buffer.sample(batch_size)
    np.random.set_state(state)  # train() draws this very batch
    model.train(gradient_steps=1, batch_size=batch_size)
    return before, batch, model.logger.name_to_value


def test_the_expectile_loss_weights_each_side_of_zero_by_hand():
    differences = th.tensor([[2.0], [-1.0], [0.5], [-3.0]])
    by_hand = (0.9 * 4.0 + 0.1 * 1.0 + 0.9 * 0.25 + 0.1 * 9.0) / 4
    assert expectile_loss(differences, 0.9).item() == pytest.approx(by_hand)
    assert expectile_loss(differences, 0.5).item() == pytest.approx(0.5 * np.mean(differences.numpy() ** 2))


@pytest.mark.parametrize(("n_steps", "q_agg"), [(1, "min"), (3, "min"), (3, "mean")])
def test_one_update_is_the_papers_losses_computed_by_hand(n_steps, q_agg):
    """Value by expectile regression on the target critics (their minimum, or with q_agg="mean" their mean), the
    actor by regression weighted by the advantages under the updated value, critics by TD to V(s') with the samples'
    n-step discounts at gamma 0.999 and shaped rewards: each logged loss equals the same computation by hand on the
    batch the step drew, with the networks as they were."""
    model = pendulum_iql(gamma=0.999, expectile=0.8, temperature=2.0, max_weight=5.0, n_steps=n_steps,
                         reward_scale=2.0, reward_bias=-1.0, q_agg=q_agg)  # fmt: skip
    before, batch, logged = one_recorded_update(model, 16)

    obs, actions = batch.observations, batch.actions
    with th.no_grad():
        twins = before.critic_target(obs, actions)
        q_data = th.min(*twins) if q_agg == "min" else (twins[0] + twins[1]) / 2
        u = q_data - before.value_net(obs)
        value_loss = (th.where(u < 0, 0.2, 0.8) * u**2).mean()
        weights = th.exp(2.0 * (q_data - model.value_net(obs))).clamp(max=5.0)  # the value after its step
        actor_loss = -(weights.squeeze(1) * before.actor.log_prob_of(obs, actions)).mean()
        discounts = batch.discounts if n_steps > 1 else 0.999
        steps = (1 - batch.discounts) / (1 - 0.999) if n_steps > 1 else 1.0
        target = 2.0 * batch.rewards - 1.0 * steps + (1 - batch.dones) * discounts * model.value_net(batch.next_observations)
        critic_loss = sum(((q - target) ** 2).mean() for q in before.critic(obs, actions))
    if n_steps > 1:
        assert (batch.discounts < 0.999).any()  # some samples summed several steps
    assert not th.allclose(q_data, th.min(*twins) if q_agg == "mean" else (twins[0] + twins[1]) / 2)
    assert logged["train/iql_q_data"] == pytest.approx(q_data.mean().item(), rel=1e-5)
    assert logged["train/value_loss"] == pytest.approx(value_loss.item(), rel=1e-5)
    assert logged["train/iql_weight"] == pytest.approx(weights.mean().item(), rel=1e-5)
    assert logged["train/actor_loss"] == pytest.approx(actor_loss.item(), rel=1e-5)
    assert logged["train/critic_loss"] == pytest.approx(critic_loss.item(), rel=1e-5)


class RecordingIQL(IQL):
    """IQL that records the hooks its update calls, in order, and halves the critics' loss."""

    def _setup_model(self):
        self.calls = []
        super()._setup_model()

    def value_loss(self, replay_data, q_data):
        self.calls.append("value_loss")
        return super().value_loss(replay_data, q_data)

    def actor_loss(self, replay_data, weights, logs):
        self.calls.append("actor_loss")
        return super().actor_loss(replay_data, weights, logs)

    def compute_target(self, replay_data, discounts):
        self.calls.append("compute_target")
        return super().compute_target(replay_data, discounts)

    def critic_loss(self, replay_data, target_q_values):
        self.calls.append("critic_loss")
        return 0.5 * super().critic_loss(replay_data, target_q_values)


def test_the_update_calls_one_hook_a_loss_in_the_papers_order_and_a_subclass_changes_one():
    """Each gradient step: the value's loss, the actor's, the critics' target and the critics' loss, each a method a
    subclass overrides; halving the critics' loss halves what the step logs and trains on, the value's step unchanged."""
    model = pendulum_iql(RecordingIQL)
    _, _, logged = one_recorded_update(model, 16)
    _, _, plain_logged = one_recorded_update(pendulum_iql(), 16)  # the same seed, batch and networks
    assert model.calls == ["value_loss", "actor_loss", "compute_target", "critic_loss"]
    assert logged["train/critic_loss"] == pytest.approx(0.5 * plain_logged["train/critic_loss"], rel=1e-5)
    assert logged["train/value_loss"] == pytest.approx(plain_logged["train/value_loss"], rel=1e-6)
    model.train(gradient_steps=2, batch_size=16)
    assert model.calls[4:] == model.calls[:4] * 2


def test_the_ddpg_awr_actor_follows_the_critics_normalised_value_anchored_by_advantage_weights_by_hand(tmp_path):
    """With actor_loss_type="ddpg_awr" the logged actor loss is -mean(Q)/mean|Q| at the actor's deterministic action
    (Q the twins' minimum, before the critics' step) plus actor_bc_weight times the squared errors to the data's
    actions, each weighted by its advantage weight over the batch's mean weight, plus the spread's negative
    log-likelihood around the detached mean. The setting is saved with the model."""
    model = pendulum_iql(actor_loss_type="ddpg_awr", actor_bc_weight=2.0, temperature=0.5, max_weight=3.0)
    before, batch, logged = one_recorded_update(model, 16)

    with th.no_grad():
        mean_actions, log_std, _ = before.actor.get_action_dist_params(batch.observations)
        q_pi = th.min(*before.critic(batch.observations, th.tanh(mean_actions)))
        squared_errors = ((th.tanh(mean_actions) - batch.actions) ** 2).mean(dim=1)
        q_data = th.min(*before.critic_target(batch.observations, batch.actions)).squeeze(1)
        weights = th.exp(0.5 * (q_data - model.value_net(batch.observations).squeeze(1))).clamp(max=3.0)
        anchor = (weights * squared_errors).mean() / weights.mean()
        spread = -th.distributions.Normal(th.tanh(mean_actions), log_std.exp()).log_prob(batch.actions).sum(-1).mean()
        by_hand = -q_pi.mean() / q_pi.abs().mean() + 2.0 * anchor + spread
    assert weights.std() > 0.01  # unequal weights: the weighted anchor differs from the plain one
    assert logged["train/actor_loss"] == pytest.approx(by_hand.item(), rel=1e-5)
    assert logged["train/actor_bc_loss"] == pytest.approx(squared_errors.mean().item(), rel=1e-5)
    model.save(tmp_path / "model.zip")
    loaded = IQL.load(tmp_path / "model.zip")
    assert (loaded.actor_loss_type, loaded.actor_bc_weight) == ("ddpg_awr", 2.0)


def test_the_ddpg_awr_actor_climbs_a_known_critic_as_far_as_its_anchor_lets_it():
    """Critics that value an action by its first coordinate (Q = a_0 + 2, fixed): without the anchor the actor's
    deterministic action climbs to a_0 near 1; with a heavy anchor it stays near the data's actions (all 0)."""
    final = {}
    for weight in (0.0, 50.0):
        model = IQL("MlpPolicy", LinearCriticEnv(), buffer_size=64, batch_size=32, policy_kwargs={"net_arch": []},
                    actor_loss_type="ddpg_awr", actor_bc_weight=weight, learning_rate=1e-2, seed=0)  # fmt: skip
        observations = np.random.default_rng(0).uniform(-1, 1, (64, 2)).astype(np.float32)
        for obs in observations:
            model.replay_buffer.add(obs, obs, np.zeros(3, np.float32), np.zeros(1), np.zeros(1), [{}])
        with th.no_grad():
            for q_net in model.critic.q_networks:
                q_net[0].weight.zero_()
                q_net[0].weight[0, 2] = 1.0
                q_net[0].bias.fill_(2.0)
        model.critic.optimizer = th.optim.SGD(model.critic.parameters(), lr=0.0)  # the critics stay as set
        model._setup_learn(1, None)
        model.train(gradient_steps=300, batch_size=32)
        with th.no_grad():
            final[weight] = model.actor(th.from_numpy(observations), deterministic=True)[:, 0].mean().item()
    assert final[0.0] > 0.9
    assert abs(final[50.0]) < 0.2


def test_the_actor_regresses_on_the_data_actions_weighted_by_advantage():
    """The actor's loss is -mean(w * log N(a | tanh(mu), std)): a finite likelihood also for actions at the bounds."""
    actor = pendulum_iql().actor
    assert isinstance(actor, IQLActor)
    obs = th.zeros(3, 3)
    actions = th.tensor([[1.0], [-1.0], [0.2]])
    mean_actions, log_std, _ = actor.get_action_dist_params(obs)
    by_hand = th.distributions.Normal(th.tanh(mean_actions), log_std.exp()).log_prob(actions).sum(-1)
    log_prob = actor.log_prob_of(obs, actions)
    assert th.isfinite(log_prob).all()
    th.testing.assert_close(log_prob, by_hand)


def test_the_actors_spread_is_one_per_dimension_bounded_and_learns_down_from_its_upper_bound():
    """The spread is the same at every state, within [exp(LOG_STD_MIN), exp(LOG_STD_MAX)], and started near its upper
    bound it still learns the data's spread: SAC's clamped head, once past its bound, gets no gradient and stays."""
    actor = pendulum_iql().actor
    obs = th.tensor([[1.0, 0.0, 0.5], [-1.0, 0.3, -2.0]])
    for logit in (-50.0, 0.0, 50.0):
        actor.log_std_logits.data.fill_(logit)
        log_std = actor.get_action_dist_params(obs)[1]
        assert log_std.shape == (2, 1) and log_std[0] == log_std[1]
        assert log_std.min() >= LOG_STD_MIN and log_std.max() <= LOG_STD_MAX
    actor.log_std_logits.data.fill_(4.0)  # std 6.5, near exp(LOG_STD_MAX)
    actions = th.from_numpy(np.random.default_rng(0).normal(0.0, 0.2, (256, 1)).astype(np.float32))
    optimizer = th.optim.Adam(actor.parameters(), lr=0.05)
    for _ in range(200):
        loss = -actor.log_prob_of(th.zeros(256, 3), actions).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    std = actor.get_action_dist_params(th.zeros(1, 3))[1].exp().item()
    assert std == pytest.approx(actions.std().item(), rel=0.2)


class LinearCriticEnv(gym.Env):
    """Box observations of 2, actions of 3 (offline training never steps it)."""

    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, True, {}


def known_critic_model(algorithm, **kwargs):
    """A model of ``algorithm`` on :class:`LinearCriticEnv` whose critics value an action by its first coordinate
    (Q = a_0, the second critic 1 higher)."""
    extra = {"cql_n_actions": 2} if algorithm is CQL else {}
    model = algorithm("MlpPolicy", LinearCriticEnv(), buffer_size=10, policy_kwargs={"net_arch": []}, seed=0,
                      **extra, **kwargs)  # fmt: skip
    with th.no_grad():
        for offset, q_net in zip((0.0, 1.0), model.critic.q_networks, strict=True):
            linear = q_net[0]  # Linear(features + actions -> 1)
            linear.weight.zero_()
            linear.weight[0, 2] = 1.0  # the first action coordinate, after the 2 observation features
            linear.bias.fill_(offset)
    return model


def chosen_and_best(policy, observations, n, scale=1.0, seed=1):
    """Best-of-``n``'s action at ``observations`` (torch's generator seeded with ``seed``), and the candidate of
    largest a_0 among the same draws, built by hand with the actor's spread times ``scale``."""
    mean_actions, log_std, _ = policy.actor.get_action_dist_params(observations)
    th.manual_seed(seed)
    chosen = policy.best_of_n_actions(observations, n, deterministic=False)
    th.manual_seed(seed)
    noise = th.randn(len(observations) * n, mean_actions.shape[1])
    spread = log_std.repeat_interleave(n, 0) + np.log(scale)
    candidates = policy.candidate_actions(mean_actions.repeat_interleave(n, 0), spread, noise)
    candidates = candidates.reshape(len(observations), n, -1)
    return chosen, candidates[th.arange(len(observations)), candidates[:, :, 0].argmax(dim=1)]


@pytest.mark.parametrize("algorithm", [IQL, CQL])
def test_best_of_n_acts_with_the_candidate_a_known_critic_values_most(algorithm):
    """Critics that value an action by its first coordinate (Q = a_0, the second critic higher still): best-of-N
    returns the sampled candidate of largest a_0, and more candidates find a larger one."""
    policy = known_critic_model(algorithm, best_of_n=16).policy
    observations = th.tensor([[0.1, -0.3], [0.5, 0.2]])
    chosen, best = chosen_and_best(policy, observations, 16)
    th.testing.assert_close(chosen, best)
    many = policy.best_of_n_actions(observations, 512, deterministic=True)
    assert (many[:, 0] >= chosen[:, 0]).all()
    assert (many[:, 0] > 0.5).all()  # the tails of the actor's spread, where one sample rarely reaches


@pytest.mark.parametrize("algorithm", [IQL, CQL])
def test_best_of_n_scale_draws_the_candidates_with_a_narrower_spread_around_the_actors_mean(algorithm):
    """With ``best_of_n_scale`` s the candidates are the actor's mean plus s times its spread: under the known critic
    (Q = a_0) the chosen action is the argmax of those candidates, not of the actor's own, and a tiny scale returns
    the actor's own action."""
    policy = known_critic_model(algorithm, best_of_n=16, best_of_n_scale=0.25).policy
    observations = th.tensor([[0.1, -0.3], [0.5, 0.2]])
    chosen, best = chosen_and_best(policy, observations, 16, scale=0.25, seed=3)
    th.testing.assert_close(chosen, best)
    _, best_of_the_actors_own = chosen_and_best(policy, observations, 16, scale=1.0, seed=3)
    assert not th.allclose(chosen, best_of_the_actors_own)
    policy.best_of_n_scale = 1e-6
    own = policy.actor(observations, deterministic=True)
    th.testing.assert_close(policy.best_of_n_actions(observations, 16, deterministic=True), own, atol=1e-4, rtol=0)


def test_best_of_n_scale_is_saved_with_the_model_and_changed_by_load(tmp_path):
    model = pendulum_iql(best_of_n=8, best_of_n_scale=0.1)
    model.save(tmp_path / "iql")
    assert IQL.load(tmp_path / "iql").policy.best_of_n_scale == 0.1
    wider = IQL.load(tmp_path / "iql", best_of_n_scale=2.0)
    assert wider.best_of_n_scale == wider.policy.best_of_n_scale == 2.0
    observation = np.array([0.3, -0.2, 0.5], dtype=np.float32)
    narrow, _ = model.predict(observation, deterministic=True)
    assert not np.allclose(wider.predict(observation, deterministic=True)[0], narrow)
    for bad in (0, -0.5, float("inf"), "0.1"):
        with pytest.raises(SettingError, match="best_of_n_scale must be a"):
            pendulum_iql(best_of_n_scale=bad)


def test_best_of_n_is_saved_with_the_model_changed_by_load_and_repeatable(tmp_path):
    model = pendulum_iql(best_of_n=8)
    model.learn(20)
    observation = np.array([0.3, -0.2, 0.5], dtype=np.float32)
    action, _ = model.predict(observation, deterministic=True)
    again, _ = model.predict(observation, deterministic=True)
    np.testing.assert_array_equal(action, again)  # the same observation, the same candidates
    model.save(tmp_path / "iql")
    loaded = IQL.load(tmp_path / "iql")
    assert loaded.policy.best_of_n == 8
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0], action)
    single = IQL.load(tmp_path / "iql", best_of_n=1)
    assert single.policy.best_of_n == 1
    np.testing.assert_allclose(single.predict(observation, deterministic=True)[0],
                               model.policy.unscale_action(np.tanh(mean_of(model, observation))), rtol=1e-5)  # fmt: skip
    with pytest.raises(SettingError, match=re.escape("best_of_n must be an integer in [1, 4096]") + ".*got 0$"):
        pendulum_iql(best_of_n=0)


def mean_of(model, observation):
    with th.no_grad():
        mean_actions, _, _ = model.actor.get_action_dist_params(th.as_tensor(observation)[None])
    return mean_actions.numpy()[0]


def test_an_averaged_actor_moves_by_its_tau_acts_for_the_model_and_is_saved_with_it(tmp_path):
    """With ``actor_average_tau`` the average starts as the actor (the normaliser's statistics too), each of the
    actor's steps moves it by tau (average' = 0.75 * average + 0.25 * actor), and predict, save and load use it; the
    critics and the value are those of the same seed without it, step for step (no loss of theirs reads the actor)."""
    model = pendulum_iql(actor_average_tau=0.25, normalize_observations=True)
    average = model.policy.actor_average
    assert average is not None and model.policy.acting_actor is average
    for mine, actors in zip(average.state_dict().values(), model.actor.state_dict().values(), strict=True):
        th.testing.assert_close(mine, actors)
    assert not th.equal(average.features_extractor.mean, th.zeros_like(average.features_extractor.mean))
    assert not any(parameter.requires_grad for parameter in average.parameters())
    before, _, _ = one_recorded_update(model, 16)
    steps = zip(average.parameters(), model.actor.parameters(), before.actor_average.parameters(), strict=True)
    for mine, actors, earlier in steps:
        th.testing.assert_close(mine, 0.75 * earlier + 0.25 * actors)
    model.learn(40)
    plain = pendulum_iql(normalize_observations=True)  # the same seed, its generators set again
    one_recorded_update(plain, 16)
    plain.learn(40)
    for network in ("critic", "value_net"):
        mine, without = getattr(model.policy, network).state_dict(), getattr(plain.policy, network).state_dict()
        assert all(th.equal(mine[key], without[key]) for key in without)
    observation = np.array([0.3, -0.2, 0.5], dtype=np.float32)
    with th.no_grad():
        features = th.as_tensor(observation)[None]
        averaged = model.policy.unscale_action(th.tanh(average.get_action_dist_params(features)[0]).numpy())[0]
    action, _ = model.predict(observation, deterministic=True)
    np.testing.assert_allclose(action, averaged, rtol=1e-5)
    assert not np.allclose(action, model.policy.unscale_action(np.tanh(mean_of(model, observation))), rtol=1e-3)
    model.save(tmp_path / "iql")
    loaded = IQL.load(tmp_path / "iql")
    assert loaded.actor_average_tau == 0.25 and loaded.policy.acting_actor is loaded.policy.actor_average
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0], action)
    plain.save(tmp_path / "plain")  # trained without an average, loaded with one: it starts as the actor
    averaged = IQL.load(tmp_path / "plain", actor_average_tau=0.25)
    for mine, actors in zip(averaged.policy.actor_average.parameters(), averaged.actor.parameters(), strict=True):
        th.testing.assert_close(mine, actors)
    np.testing.assert_array_equal(
        averaged.predict(observation, deterministic=True)[0], plain.predict(observation, deterministic=True)[0]
    )


def test_best_of_n_ranks_whole_chunks_and_runs_them_open_loop():
    model = pendulum_iql(best_of_n=4, action_chunk=3)
    model.learn(10)
    observation = np.array([0.3, -0.2, 0.5], dtype=np.float32)
    action, state = model.predict(observation, deterministic=True)
    chunk = state[0][0]
    assert chunk.shape == (3, 1)
    second, state = model.predict(observation + 1, state, deterministic=True)
    np.testing.assert_array_equal(second, chunk[1])  # open loop: the chunk's next action, whatever the observation


def test_a_sparse_task_at_gamma_0_999_backs_up_30_steps_on_the_success_scale():
    """Reward 1 at the end of a terminated episode, gamma 0.999 and 30-step backups: a sample that reaches the success
    k steps ahead has the target 0.999^(k-1), the others bootstrap on V(s') with 0.999 to the steps they summed."""
    env = spaces_env(spaces.Box(-1.0, 1.0, (1,), np.float32), spaces.Box(-1.0, 1.0, (1,), np.float32))
    buffer = ReplayBuffer(400, env.observation_space, env.action_space)
    for episode in range(10):
        for step in range(40):
            done = step == 39
            reward = 1.0 if done and episode % 2 == 0 else 0.0
            buffer.add(np.array([step / 40]), np.array([(step + 1) / 40]), np.array([0.1]), np.array([reward]),
                       np.array([done]), [{"TimeLimit.truncated": done and reward == 0}])  # fmt: skip
    model = IQL("MlpPolicy", env, dataset=buffer, gamma=0.999, n_steps=30, batch_size=64, policy_kwargs=TINY, seed=0)
    model.learn(5)
    batch = model.replay_buffer.sample(512)
    with th.no_grad():
        targets = model.compute_target(batch, batch.discounts)
        bootstrap = batch.discounts * model.value_net(batch.next_observations)
    reached = (batch.dones > 0).flatten()
    steps_ahead = 40 - th.round(batch.observations[reached, 0] * 40)
    assert reached.any() and (~reached).any()
    th.testing.assert_close(targets[reached, 0], 0.999 ** (steps_ahead - 1))
    th.testing.assert_close(targets[~reached], bootstrap[~reached])
    summed = th.round(th.log(batch.discounts[~reached]) / np.log(0.999))
    assert set(summed.int().flatten().tolist()) <= set(range(1, 31)) and (summed == 30).any()


def test_a_target_floor_raises_the_targets_below_it_and_leaves_the_others():
    """Zero rewards and a value network that says -5 at every state: the targets, -5 times the samples' discounts,
    sink below the floor of 0, which raises them to it; at +5 they stay r + discount * V(s'), as without a floor."""
    model = pendulum_iql(gamma=0.999, n_steps=3, reward_scale=0.0, target_floor=0.0)
    batch = model.replay_buffer.sample(64)
    last = model.value_net.v_net[-1]
    with th.no_grad():
        last.weight.zero_()
        last.bias.fill_(-5.0)
        sunk = model.compute_target(batch, batch.discounts)
        model.target_floor = None
        unfloored = model.compute_target(batch, batch.discounts)
        model.target_floor = 0.0
        last.bias.fill_(5.0)
        raised = model.compute_target(batch, batch.discounts)
    assert not batch.dones.any()  # Pendulum's episodes end by the time limit only
    th.testing.assert_close(unfloored, -5.0 * batch.discounts)
    assert th.equal(sunk, th.zeros_like(sunk))
    th.testing.assert_close(raised, 5.0 * batch.discounts)


def test_a_target_ceiling_lowers_the_targets_above_it_and_leaves_the_others():
    """The floor's mirror: at a value of +5 the targets, 5 times the samples' discounts, rise above the ceiling of 1,
    which lowers them to it; at -5 they stay r + discount * V(s'), and the floor and the ceiling act together."""
    model = pendulum_iql(gamma=0.999, n_steps=3, reward_scale=0.0, target_ceiling=1.0)
    batch = model.replay_buffer.sample(64)
    last = model.value_net.v_net[-1]
    with th.no_grad():
        last.weight.zero_()
        last.bias.fill_(5.0)
        lowered = model.compute_target(batch, batch.discounts)
        last.bias.fill_(-5.0)
        kept = model.compute_target(batch, batch.discounts)
        model.target_floor = 0.0
        raised = model.compute_target(batch, batch.discounts)
    assert th.equal(lowered, th.ones_like(lowered))
    th.testing.assert_close(kept, -5.0 * batch.discounts)
    assert th.equal(raised, th.zeros_like(raised))


def test_calibrated_cql_at_gamma_0_999_bounds_by_returns_in_the_same_gamma_and_rewards():
    env = spaces_env(spaces.Box(-1.0, 1.0, (1,), np.float32), spaces.Box(-1.0, 1.0, (1,), np.float32))
    buffer = ReplayBuffer(20, env.observation_space, env.action_space)
    for step in range(5):
        buffer.add(np.array([step]), np.array([step + 1]), np.array([0.0]), np.array([float(step == 4)]),
                   np.array([step == 4]), [{"TimeLimit.truncated": False}])  # fmt: skip
    model = CalQL("MlpPolicy", env, dataset=buffer, gamma=0.999, reward_scale=4.0, reward_bias=-2.0, batch_size=4,
                  cql_n_actions=2, policy_kwargs=TINY, seed=0)  # fmt: skip
    expected = returns_to_go([-2.0, -2.0, -2.0, -2.0, 2.0], truncated=False, gamma=0.999)
    np.testing.assert_allclose(model.replay_buffer.returns_to_go[:5, 0], expected, rtol=1e-6)
    np.testing.assert_allclose(expected[0], -2 * (1 - 0.999**4) / (1 - 0.999) + 2 * 0.999**4, rtol=1e-6)
    model.learn(5)


def test_a_diverging_update_stops_with_one_line_before_the_step():
    model = pendulum_iql(reward_scale=1e38, learning_rate=1.0)
    with pytest.raises(TrainingDivergedError, match=r"IQL's \w+ loss is (nan|inf) at gradient step \d+: training diverged"):
        model.learn(200)


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"expectile": 1.0}, r"expectile must be in \[0.5, 1\), got 1.0"),
        ({"expectile": 0.3}, r"expectile must be in \[0.5, 1\), got 0.3"),
        ({"temperature": -1.0}, r"temperature must be a (finite )?number >= 0, got -1.0"),
        ({"max_weight": 0.0}, r"max_weight must be a (finite )?number > 0, got 0.0"),
        ({"reward_bias": float("nan")}, "reward_bias must be a finite number, got nan"),
        ({"q_agg": "max"}, "q_agg must be one of 'min', 'mean', got 'max'"),
        ({"actor_loss_type": "td3"}, "actor_loss_type must be one of 'awr', 'ddpg_awr', got 'td3'"),
        ({"actor_bc_weight": -1.0}, r"actor_bc_weight must be a (finite )?number >= 0, got -1.0"),
        ({"target_floor": float("-inf")}, "target_floor must be a finite number, got -inf"),
        ({"target_floor": "0"}, "target_floor must be a finite number, got '0'"),
        ({"target_ceiling": float("nan")}, "target_ceiling must be a finite number, got nan"),
        ({"target_floor": 1.0, "target_ceiling": 0.0}, "target_ceiling 0.0 is below target_floor 1.0"),
        ({"actor_average_tau": 0.0}, r"actor_average_tau must be a number in \(0, 1\] or None, got 0.0"),
        ({"actor_average_tau": "0.01"}, r"actor_average_tau must be a number in \(0, 1\] or None, got '0.01'"),
    ],
)
def test_settings_outside_their_range_are_one_line(keywords, message):
    with pytest.raises(SettingError, match=message):
        pendulum_iql(**keywords)


def sparse_minari_dataset(tmp_path, monkeypatch) -> minari.MinariDataset:
    """Six episodes of a one-dimensional task whose returns are 0, 1, 2, 3, 4, 5."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    env = gym.make("Pendulum-v1")
    episodes = []
    for episode in range(6):
        rewards = np.zeros(8)
        rewards[:episode] = 1.0
        observations = np.full((9, 3), float(episode), dtype=np.float32)
        episodes.append(minari.data_collector.EpisodeBuffer(
            observations=observations, actions=np.full((8, 1), episode / 10, dtype=np.float32), rewards=rewards,
            terminations=np.zeros(8, bool), truncations=np.eye(8, dtype=bool)[-1],
        ))  # fmt: skip
    return minari.create_dataset_from_buffers("test/returns-v0", episodes, env=env, algorithm_name="t", author="t",
                                              author_email="t", code_permalink="t", description="t")  # fmt: skip


@pytest.mark.parametrize(
    ("keywords", "kept"),
    [({"min_return": 4.0}, {4, 5}), ({"top_fraction": 0.5}, {3, 4, 5}), ({"min_return": 1.0, "top_fraction": 0.2}, {5})],
)
def test_filtered_behaviour_cloning_loads_the_selected_episodes_only(tmp_path, monkeypatch, keywords, kept):
    dataset = sparse_minari_dataset(tmp_path, monkeypatch)
    model = BC("MlpPolicy", gym.make("Pendulum-v1"), dataset=dataset, batch_size=4, policy_kwargs=TINY,
               normalize_observations=False, **keywords)  # fmt: skip
    size = model.replay_buffer.size()
    assert size == 8 * len(kept)
    assert set(model.replay_buffer.observations[:size, 0, 0].astype(int).tolist()) == kept
    model.learn(3)


def test_filtered_behaviour_cloning_refuses_what_it_cannot_select(tmp_path, monkeypatch):
    dataset = sparse_minari_dataset(tmp_path, monkeypatch)
    env = gym.make("Pendulum-v1")
    with pytest.raises(SettingError, match=r"no episode of test/returns-v0 has a return >= 9 \(it has 6 episodes, the "
                                           r"highest return 5\)"):  # fmt: skip
        BC("MlpPolicy", env, dataset=dataset, min_return=9.0)
    with pytest.raises(SettingError, match=r"top_fraction must be in \(0, 1\] or None, got 0"):
        BC("MlpPolicy", env, dataset=dataset, top_fraction=0)
    with pytest.raises(SettingError, match="a replay buffer has no episodes to select"):
        BC("MlpPolicy", env, dataset=random_rollouts(gym.make("Pendulum-v1"), 20), min_return=1.0)


def test_iql_refuses_the_keywords_of_an_entropy_term_it_does_not_have():
    assert "ent_coef" not in IQL.known_keywords() and {"batch_size", "reward_scale", "online_fraction"} <= IQL.known_keywords()
    with pytest.raises(KeywordError, match=r"^IQL does not take ent_coef, target_entropy: its actor has no entropy term$"):
        IQL("MlpPolicy", "Pendulum-v1", ent_coef=0.1, target_entropy=-1.0)


@pytest.mark.parametrize("algorithm", [IQL, CQL])
def test_the_actor_loss_reads_the_critics_without_computing_the_gradients_of_their_weights(algorithm):
    """The actor's loss back-propagates through the critics to the actions and stops there: the actor's gradients are
    those of the same loss through trainable critics (by hand), the critics get none, and stay trainable after."""
    if algorithm is IQL:
        model = pendulum_iql(actor_loss_type="ddpg_awr", actor_bc_weight=2.0)
    else:
        model = CQL("MlpPolicy", gym.make("Pendulum-v1"), dataset=random_rollouts(gym.make("Pendulum-v1"), 300),
                    batch_size=16, seed=0, policy_kwargs=TINY, bc_steps=0, actor_bc_weight=0.0)  # fmt: skip
    batch = model.replay_buffer.sample(16)
    mean_actions, log_std, _ = model.actor.get_action_dist_params(batch.observations)
    if algorithm is IQL:
        loss = model.ddpg_actor_loss(batch, th.ones(16), {})
        actions_pi = th.tanh(mean_actions)
        q_pi = th.min(*model.critic(batch.observations, actions_pi)).squeeze(1)
        spread = -th.distributions.Normal(actions_pi.detach(), log_std.exp()).log_prob(batch.actions).sum(-1).mean()
        squared_errors = ((actions_pi - batch.actions) ** 2).mean(dim=1)
        by_hand = -q_pi.mean() / q_pi.abs().mean().detach() + 2.0 * squared_errors.mean() + spread
    else:
        actions_pi, log_prob = model.actor.action_dist.log_prob_from_params(mean_actions, log_std)
        ent_coef = th.tensor(0.1)
        loss = model.compute_actor_loss(batch, (mean_actions, log_std), actions_pi, log_prob.reshape(-1, 1), ent_coef, {})
        q_pi = th.min(*model.critic(batch.observations, actions_pi))
        by_hand = (ent_coef * log_prob.reshape(-1, 1) - q_pi).mean()
    actor_parameters = list(model.actor.parameters())
    gradients = th.autograd.grad(loss, actor_parameters, retain_graph=True)
    loss.backward(retain_graph=True)  # the actor's part of the graph is by_hand's too
    assert all(parameter.grad is None for parameter in model.critic.parameters())
    assert all(parameter.requires_grad for parameter in model.critic.parameters())
    assert by_hand.item() == pytest.approx(loss.item(), rel=1e-6)
    for mine, theirs in zip(gradients, th.autograd.grad(by_hand, actor_parameters, retain_graph=True), strict=True):
        assert th.allclose(mine, theirs, rtol=1e-5, atol=1e-7)
    by_hand.backward()
    assert all(parameter.grad is not None for parameter in model.critic.parameters())  # the check can tell
