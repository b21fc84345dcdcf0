"""Implicit Q-Learning (IQL) for offline RL: a critic trained in sample, an actor by advantage-weighted regression."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, ReplayBufferSamples, Schedule
from stable_baselines3.common.utils import polyak_update, update_learning_rate
from torch.nn import functional as F

from sb3_cql.common.offline import (
    OfflineSAC,
    SettingError,
    behaviour_cloning_loss,
    check_finite,
    check_non_negative,
    finite_loss_value,
    shaped_rewards,
)
from sb3_cql.iql.policies import CnnPolicy, IQLPolicy, MlpPolicy, MultiInputPolicy, ValueNetwork

if TYPE_CHECKING:
    from minari import MinariDataset


def expectile_loss(differences: th.Tensor, expectile: float) -> th.Tensor:
    """The expectile regression loss of IQL's value, ``mean(|expectile - 1(u < 0)| * u^2)`` over the
    ``differences`` ``u = Q(s, a) - V(s)``: ``expectile`` 0.5 is the mean squared error, above 0.5 the value
    approaches the upper expectile of Q over the data's actions (their in-sample maximum as it nears 1)."""
    weight = th.where(differences < 0, 1.0 - expectile, expectile)
    return (weight * differences.pow(2)).mean()


def expectile_bce_loss(logits: th.Tensor, targets: th.Tensor, expectile: float) -> th.Tensor:
    """The expectile loss on the success scale (``value_loss_type="bce"``): the binary cross-entropy of the value's
    ``logits`` against the ``targets`` in [0, 1], each weighted ``|expectile - 1(u < 0)|`` with ``u = target -
    sigmoid(logit)``. At ``expectile`` 0.5 its minimum is the mean of the targets (SHARSA's value loss, halved, as
    :func:`expectile_loss` halves the squared error); above 0.5 it leans to the higher targets."""
    weight = th.where(targets < th.sigmoid(logits), 1.0 - expectile, expectile)
    return (weight * F.binary_cross_entropy_with_logits(logits, targets, reduction="none")).mean()


class IQL(OfflineSAC):
    """Implicit Q-Learning (Kostrikov, Nair and Levine 2021, https://arxiv.org/abs/2110.06169), trained offline.

    Every loss reads only the data's actions, so the values stay on the scale of the data's returns (no policy sample
    and no maximum in the backup, nothing pushed down). Each gradient step, in the reference code's order:

    - the value, by expectile regression on the target critics at the data's actions:
      ``L_V = E[|expectile - 1(u < 0)| u^2]``, ``u = min_i Q'_i(s, a) - V(s)`` (:func:`expectile_loss`; the twins'
      mean instead of their minimum with ``q_agg="mean"``);
    - the actor, by advantage-weighted regression: ``L_pi = -E[min(exp(temperature * (Q'(s, a) - V(s))),
      max_weight) * log pi(a | s)]``, ``pi`` the Gaussian of :class:`~sb3_cql.iql.policies.IQLActor`;
    - the twin critics, by TD to the value of the next state: ``L_Q = sum_i E[(Q_i(s, a) - r - (1 - d) * discount *
      V(s'))^2]`` (each critic's full mean squared error, as the references), with SB3's n-step ``discounts``
      (``n_steps``, ``action_chunk``) and the critics' rewards ``reward_scale * r + reward_bias``;
    - the target critics, by Polyak averaging with ``tau``.

    With ``actor_loss_type="ddpg_bc"`` the actor follows the critics' gradient instead, anchored to the data (DDPG+BC,
    the extraction Park et al. 2024, https://arxiv.org/abs/2406.09329, found ahead of AWR on most tasks, as in
    TD3+BC): ``L_pi = -E[Q(s, tanh(mu(s)))] / E[|Q(s, tanh(mu(s)))|] + actor_bc_weight * E[(tanh(mu(s)) - a)^2]``,
    ``Q`` the minimum of the twins and the denominator detached (:func:`~sb3_cql.common.offline.behaviour_cloning_loss`
    and the normalisation of CQL's ``actor_bc_weight``); the spread, which only the actor's samples and best-of-N
    use, is fitted to the data's actions around the detached mean by likelihood. ``"ddpg_awr"`` weights each sample's
    squared error in that imitation by AWR's weight, ``min(exp(temperature * (Q'(s, a) - V(s))), max_weight)``,
    divided by the batch's mean weight (so ``actor_bc_weight`` keeps its scale): the critics' gradient refines the
    action while the imitation leans to the data's better actions.

    With ``value_loss_type="bce"`` the critics and the value are on the success scale, as SHARSA's (Park et al. 2025):
    each network gives a logit, its value is the sigmoid of it (in (0, 1)), the TD targets ``r + (1 - d) * discount *
    sigmoid(V(s'))`` and the twins' values are regressed by binary cross-entropy (:func:`expectile_bce_loss` for the
    value), so no value can sink below a failure's 0 or rise above a success's 1. It needs rewards that are discounted
    success probabilities: ``reward_scale * r + reward_bias`` in [0, 1] at every step of the data (a sparse 0/1
    reward that ends the episode).

    Everything else is :class:`~sb3_cql.common.OfflineSAC`'s: datasets (Minari ids, objects, SB3 buffers),
    ``n_steps``, ``action_chunk``, the observation normaliser, ``save``/``load``, callbacks and online fine-tuning
    (``online_fraction``: the same losses on mixed batches, acting with samples of the actor). With ``best_of_n``
    the model acts by ranking ``best_of_n`` samples of its actor by its critics (SHARSA's best-of-N), which uses the
    critics where the actor's regression only weights the data.

    Defaults are the reference implementations' for a generic task (ikostrikov/implicit_q_learning's MuJoCo settings
    and d3rlpy's ``IQLConfig``: learning rates 3e-4, batch 256, ``expectile`` 0.7, ``temperature`` 3, weights
    clipped at 100, ``tau`` 5e-3, gamma 0.99, 2 x 256 networks, raw observations); its AntMaze settings, for sparse
    long-horizon goals, are ``expectile`` 0.9, ``temperature`` 10, rewards ``r - 1``.

    :param policy: the policy model (``"MlpPolicy"``, ``"CnnPolicy"``, ``"MultiInputPolicy"``: SAC's, with IQL's
        actor and value network, :mod:`sb3_cql.iql.policies`).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id, or a filled ``ReplayBuffer``; ``None`` for an empty buffer of
        ``buffer_size``. A missing standard id is collected first (:func:`sb3_cql.data.ensure_dataset`).
    :param learning_rate: learning rate of the critics and the value network.
    :param actor_learning_rate: learning rate of the actor; ``None`` for ``learning_rate``.
    :param buffer_size: size of an empty replay buffer when ``dataset`` is ``None``.
    :param batch_size: minibatch size of each gradient step.
    :param tau: Polyak coefficient of the target critics.
    :param gamma: discount factor (up to 1; 0.999 for goals hundreds of steps after the choice that decides them).
    :param expectile: the value's expectile of Q over the data's actions, in [0.5, 1): 0.5 is SARSA's mean, higher is
        closer to the best action the data show.
    :param temperature: inverse temperature of the advantage weights (0: plain behaviour cloning); unused by
        ``"ddpg_bc"``.
    :param max_weight: the largest advantage weight.
    :param actor_loss_type: how the actor is extracted from the critics: ``"awr"`` (the paper's advantage-weighted
        regression), ``"ddpg_bc"`` (the critics' gradient at the actor's action, anchored to the data) or
        ``"ddpg_awr"`` (the same, the anchor weighted by AWR's weights); see above.
    :param actor_bc_weight: with ``"ddpg_bc"`` and ``"ddpg_awr"``, the weight of the imitation against the critics'
        normalised value, as CQL's (TD3+BC's ``alpha`` is ``1 / actor_bc_weight``; its default 2.5 is 0.4 here).
    :param target_update_interval: gradient steps between target updates.
    :param reward_scale: the critics learn from ``reward_scale * reward + reward_bias`` (the buffer keeps the data's
        rewards); a sparse 0/1 reward that ends the episode needs neither: the values are then the discounted
        probability of success, in [0, 1].
    :param reward_bias: see ``reward_scale``.
    :param value_loss_type: ``"squared"`` (the references' squared errors) or ``"bce"`` (values on the success scale,
        trained by binary cross-entropy; see above).
    :param q_agg: how the twin target critics combine into the value's target and the advantages: ``"min"`` (the
        references') or ``"mean"`` (SHARSA's other choice; the minimum's downward bias compounds over long backups).
        Best-of-N ranks by the minimum either way.
    :param target_floor: the least TD target the critics learn, in their units (after ``reward_scale`` and
        ``reward_bias``): a target below it is raised to it. ``None`` (the default, the references') leaves the
        targets as they are. Rewards of at least 0 give no return below 0 (``reward_bias / (1 - gamma)`` with a
        negative ``reward_bias``), and a floor there keeps the twins' minimum from sinking the values below every
        return the data can have over long backups.
    :param actor_average_tau: act with an exponential moving average of the actor's weights: after each of the
        actor's steps the average moves towards it by this Polyak coefficient (``average = (1 - actor_average_tau) *
        average + actor_average_tau * actor``; 0.001 averages over about the last 1,000 steps), and the model acts with
        the average (``predict``, evaluations, best-of-N's candidates; :class:`~sb3_cql.iql.policies.IQLPolicy`'s
        ``actor_average``), while the actor goes on learning. It damps the swings of an actor that follows a moving
        critic between one checkpoint and the next. ``None`` (the default, the references'): act with the actor.
    :param best_of_n: act by ranking ``best_of_n`` candidates from the actor by the critics
        (:class:`~sb3_cql.common.policies.OfflinePolicy`); saved with the model. ``1``: the actor's own action.
    :param best_of_n_scale: the candidates' standard deviation as a multiple of the actor's (``1``, the default: the
        actor's own distribution); saved with the model.
    :param normalize_observations: z-score the observations with the dataset's mean and std inside the policy;
        ``False`` (the default, as the references) reads them raw; ``None`` z-scores them for an ``MlpPolicy`` on Box
        observations. On a sparse task of hand-made data, z-scored observations made the critics' advantages noisier
        and the advantage-weighted actor failed where raw ones succeeded, in d3rlpy's IQL too (``docs/benchmarks.md``).
    :param online_fraction: ``None`` (the default) trains offline; a fraction fine-tunes online with the offline data
        kept (:class:`~sb3_cql.common.OfflineSAC`).
    :param online_buffer_size: capacity of the online transitions when fine-tuning.
    :param learning_starts: env steps of uniform random actions before training starts, when fine-tuning (SAC's).
    :param train_freq: env steps (or ``(n, "episode")``) between two trainings, when fine-tuning (SAC's).
    :param gradient_steps: gradient steps of each training, when fine-tuning (SAC's).
    :param action_noise: noise added to the actions when fine-tuning (SB3's ``ActionNoise``).
    :param deterministic_rollouts: when fine-tuning, act with the deterministic action plus ``action_noise``.
    :param action_chunk: actions per decision (Q-chunking): the actor and the critics work on chunks, the TD target
        spans the chunk; each chunk runs open loop when the model acts. ``1``: one action a state.
    :param replay_buffer_class: the class of the replay buffer the data load into (SAC's).
    :param replay_buffer_kwargs: keywords of that class (SAC's).
    :param optimize_memory_usage: SAC's; only ``False``.
    :param n_steps: SB3's n-step returns: the TD target sums up to ``n_steps`` rewards within an episode and
        bootstraps on ``V`` with ``gamma`` to the power of the steps summed.
    :param stats_window_size: episodes averaged in the rollout logs when fine-tuning (SAC's).
    :param tensorboard_log: TensorBoard log folder.
    :param policy_kwargs: keywords of the policy (``net_arch``, ``critic_layer_norm``, ...).
    :param verbose: 0 silent, 1 training logs, 2 debug.
    :param seed: seed of the random generators.
    :param device: torch device.
    :param _init_setup_model: build the networks now.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: IQLPolicy
    value_net: ValueNetwork

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str,
        dataset: MinariDataset | str | ReplayBuffer | None = None,
        learning_rate: float | Schedule = 3e-4,
        actor_learning_rate: float | Schedule | None = None,
        buffer_size: int = 2_000_000,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        expectile: float = 0.7,
        temperature: float = 3.0,
        max_weight: float = 100.0,
        actor_loss_type: str = "awr",
        actor_bc_weight: float = 0.4,
        target_update_interval: int = 1,
        reward_scale: float = 1.0,
        reward_bias: float = 0.0,
        value_loss_type: str = "squared",
        q_agg: str = "min",
        target_floor: float | None = None,
        actor_average_tau: float | None = None,
        best_of_n: int = 1,
        best_of_n_scale: float = 1.0,
        normalize_observations: bool | None = False,
        online_fraction: float | None = None,
        online_buffer_size: int = 1_000_000,
        learning_starts: int = 0,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        deterministic_rollouts: bool = False,
        action_chunk: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        self.expectile = expectile
        self.temperature = temperature
        self.max_weight = max_weight
        self.actor_loss_type = actor_loss_type
        self.actor_bc_weight = actor_bc_weight
        self.reward_scale = reward_scale
        self.reward_bias = reward_bias
        self.value_loss_type = value_loss_type
        self.q_agg = q_agg
        self.target_floor = target_floor
        self.actor_average_tau = actor_average_tau
        super().__init__(
            policy,
            env,
            dataset=dataset,
            learning_rate=learning_rate,
            actor_learning_rate=actor_learning_rate,
            buffer_size=buffer_size,
            normalize_observations=normalize_observations,
            online_fraction=online_fraction,
            online_buffer_size=online_buffer_size,
            learning_starts=learning_starts,
            action_noise=action_noise,
            deterministic_rollouts=deterministic_rollouts,
            action_chunk=action_chunk,
            best_of_n=best_of_n,
            best_of_n_scale=best_of_n_scale,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            stats_window_size=stats_window_size,
            policy_kwargs=policy_kwargs,
            batch_size=batch_size,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            tau=tau,
            gamma=gamma,
            ent_coef=0.0,  # no entropy term: SAC's coefficient stays a constant, never learned
            target_update_interval=target_update_interval,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=_init_setup_model,
        )

    def _check_settings(self) -> None:
        """OfflineSAC's checks, and those of IQL's own settings."""
        super()._check_settings()
        expectile = self.expectile
        if not (isinstance(expectile, (int, float)) and not isinstance(expectile, bool) and 0.5 <= expectile < 1):
            raise SettingError(f"expectile must be in [0.5, 1), got {expectile!r}")
        check_non_negative([("temperature", self.temperature)])
        check_non_negative([("max_weight", self.max_weight)], strictly=True)
        check_non_negative([("actor_bc_weight", self.actor_bc_weight)])
        check_finite([("reward_scale", self.reward_scale), ("reward_bias", self.reward_bias)])
        if self.target_floor is not None:
            check_finite([("target_floor", self.target_floor)])
        tau = self.actor_average_tau
        if tau is not None and not (isinstance(tau, (int, float)) and not isinstance(tau, bool) and 0 < tau <= 1):
            raise SettingError(f"actor_average_tau must be a number in (0, 1] or None, got {tau!r}")
        for name, choices in (
            ("value_loss_type", ("squared", "bce")),
            ("q_agg", ("min", "mean")),
            ("actor_loss_type", ("awr", "ddpg_bc", "ddpg_awr")),
        ):
            if getattr(self, name) not in choices:
                raise SettingError(f"{name} must be one of {', '.join(map(repr, choices))}, got {getattr(self, name)!r}")
        if self.n_steps > 1 and self.reward_bias != 0 and self.gamma >= 1:
            raise SettingError("reward_bias with n_steps > 1 needs gamma < 1: the bias is summed over the steps of a sample")
        if not issubclass(self.policy_class, IQLPolicy):
            name = getattr(self.policy_class, "__name__", self.policy_class)
            raise SettingError(f"IQL needs a policy with a value network (sb3_cql.iql.policies), got {name}")

    def _setup_model(self) -> None:
        if self.actor_average_tau is not None:
            self.policy_kwargs["average_actor"] = True  # saved with the model, so a loaded one acts with its average
        super()._setup_model()

    def _create_aliases(self) -> None:
        super()._create_aliases()
        self.value_net = self.policy.value_net

    def _fill_from_dataset(self, dataset: MinariDataset | str | ReplayBuffer) -> None:
        """OfflineSAC's, then, on the success scale, a check that the critics' rewards are in [0, 1]."""
        super()._fill_from_dataset(dataset)
        if self.value_loss_type == "bce":
            rewards = self.reward_scale * self.replay_buffer.rewards[: self.replay_buffer.size()] + self.reward_bias
            if rewards.size and (rewards.min() < 0 or rewards.max() > 1):
                raise SettingError(
                    f'value_loss_type="bce" needs the critics\' rewards (reward_scale * reward + reward_bias) in [0, 1], '
                    f"the data give {rewards.min():g} to {rewards.max():g}: set reward_scale and reward_bias so that a "
                    'success is 1 and every other step 0, or use value_loss_type="squared"'
                )

    def as_values(self, outputs: th.Tensor) -> th.Tensor:
        """The critics' or the value network's ``outputs`` as values: themselves, or their sigmoid on the success
        scale (``value_loss_type="bce"``)."""
        return th.sigmoid(outputs) if self.value_loss_type == "bce" else outputs

    def target_q_values(self, observations: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """The target twins' values of the data's actions, combined by ``q_agg`` (their minimum or their mean)."""
        q_values = self.as_values(th.cat(self.critic_target(observations, actions), dim=1))
        if self.q_agg == "mean":
            return q_values.mean(dim=1, keepdim=True)
        return q_values.min(dim=1, keepdim=True).values

    def train(self, gradient_steps: int, batch_size: int = 256) -> None:
        """IQL's update (the class docstring), ``gradient_steps`` times: the value, the actor, the critics, the
        targets. Logs SB3's ``train/actor_loss`` and ``train/critic_loss``, and ``train/value_loss``,
        ``train/iql_q_data``, ``train/iql_value``, ``train/iql_advantage``, ``train/iql_weight`` (the mean
        advantage weight), and with the DDPG extractions ``train/actor_bc_loss`` (their imitation, unweighted)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.critic.optimizer, self.value_net.optimizer])
        update_learning_rate(self.actor.optimizer, self.actor_lr_schedule(self._current_progress_remaining))
        logs: dict[str, list[float]] = {}

        for _ in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma

            with th.no_grad():
                q_data = self.target_q_values(replay_data.observations, replay_data.actions)
            value_output = self.value_net(replay_data.observations)
            if self.value_loss_type == "bce":
                value_loss = expectile_bce_loss(value_output, q_data, self.expectile)
            else:
                value_loss = expectile_loss(q_data - value_output, self.expectile)
            self._step(self.value_net.optimizer, value_loss, "IQL's value loss")

            with th.no_grad():
                value = self.as_values(self.value_net(replay_data.observations))
                advantage = q_data - value
            weights = th.exp(self.temperature * advantage).clamp(max=self.max_weight).squeeze(1)
            if self.actor_loss_type == "awr":
                log_prob = self.actor.log_prob_of(replay_data.observations, replay_data.actions)
                actor_loss = -(weights * log_prob).mean()
            else:
                imitation_weights = weights / weights.mean() if self.actor_loss_type == "ddpg_awr" else None
                actor_loss = self.ddpg_bc_actor_loss(replay_data, logs, imitation_weights)
            self._step(self.actor.optimizer, actor_loss, "IQL's actor loss")
            if self.actor_average_tau is not None:  # the policy then keeps an average (_setup_model)
                polyak_update(self.actor.parameters(), self.policy.actor_average.parameters(), self.actor_average_tau)

            with th.no_grad():
                target_q_values = self.compute_target(replay_data, discounts)
            current_q_values = self.critic(replay_data.observations, replay_data.actions)
            if self.value_loss_type == "bce":
                critic_loss = sum(F.binary_cross_entropy_with_logits(q, target_q_values) for q in current_q_values)
            else:
                critic_loss = sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
            critic_loss_value = self._step(self.critic.optimizer, critic_loss, "IQL's critic loss")

            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

            for key, number in (
                ("train/critic_loss", critic_loss_value),
                ("train/value_loss", value_loss.item()),
                ("train/actor_loss", actor_loss.item()),
                ("train/iql_q_data", q_data.mean().item()),
                ("train/iql_value", value.mean().item()),
                ("train/iql_advantage", advantage.mean().item()),
                ("train/iql_weight", weights.mean().item()),
            ):
                logs.setdefault(key, []).append(number)

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(key, float(np.mean(values)))

    def ddpg_bc_actor_loss(
        self,
        replay_data: ReplayBufferSamples,
        logs: dict[str, list[float]],
        imitation_weights: th.Tensor | None = None,
    ) -> th.Tensor:
        """The actor's loss with ``actor_loss_type`` ``"ddpg_bc"`` or ``"ddpg_awr"`` (the class docstring): the
        critics' minimum at the actor's deterministic action, divided by its batch mean ``|Q|`` (detached), against
        ``actor_bc_weight`` times the imitation of the data's actions, each sample's squared error weighted by
        ``imitation_weights`` (``(batch,)``, ``None``: equally); plus the spread's likelihood of the data's actions
        around the detached mean. Logs ``train/actor_bc_loss``, the unweighted imitation."""
        mean_actions, log_std, _ = self.actor.get_action_dist_params(replay_data.observations)
        actions_pi = th.tanh(mean_actions)
        q_pi = self.as_values(th.cat(self.critic(replay_data.observations, actions_pi), dim=1)).min(dim=1).values
        bc_loss = behaviour_cloning_loss(mean_actions, replay_data.actions)
        logs.setdefault("train/actor_bc_loss", []).append(bc_loss.item())
        if imitation_weights is not None:
            bc_loss = (imitation_weights * (actions_pi - replay_data.actions).pow(2).mean(dim=-1)).mean()
        spread = th.distributions.Normal(actions_pi.detach(), log_std.exp())
        spread_loss = -spread.log_prob(replay_data.actions).sum(dim=-1).mean()
        return -q_pi.mean() / q_pi.abs().mean().detach().clamp(min=1e-6) + self.actor_bc_weight * bc_loss + spread_loss

    def critic_rewards(self, replay_data: ReplayBufferSamples) -> th.Tensor:
        """The rewards the critics learn from: ``reward_scale * reward + reward_bias`` a step, summed over an n-step
        sample's steps with their discounts (:func:`~sb3_cql.common.offline.shaped_rewards`)."""
        return shaped_rewards(replay_data, self.reward_scale, self.reward_bias, self.gamma)

    def compute_target(self, replay_data: ReplayBufferSamples, discounts: th.Tensor | float) -> th.Tensor:
        """The critics' TD target, ``rewards + (1 - dones) * discounts * V(s')`` (:meth:`critic_rewards`; the
        samples' ``discounts`` for n-step returns, else ``gamma``), raised to ``target_floor`` where it is set; on the
        success scale ``V(s')`` is the value network's sigmoid and the target is kept in [0, 1] (a reward of 1 that
        does not end the episode, met online, would take it above)."""
        next_values = self.as_values(self.value_net(replay_data.next_observations))
        target = self.critic_rewards(replay_data) + (1 - replay_data.dones) * discounts * next_values
        if self.target_floor is not None:
            target = target.clamp(min=self.target_floor)
        return target.clamp(0.0, 1.0) if self.value_loss_type == "bce" else target

    def _step(self, optimizer: th.optim.Optimizer, loss: th.Tensor, description: str) -> float:
        """One optimizer step on ``loss``, refused (:class:`~sb3_cql.common.TrainingDivergedError`) before it is taken
        if the loss is NaN or infinite; the loss as a number."""
        hint = "try a lower learning_rate, a lower temperature, or rewards on a smaller scale"
        value = finite_loss_value(loss, description, self.num_timesteps + 1, hint)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return value

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "value_net.optimizer"], variables

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "value_net"]
