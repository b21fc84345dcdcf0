"""Conservative Q-Learning (CQL(H)) for offline RL: SAC plus a conservative term in the critic loss."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, ReplayBufferSamples, Schedule
from stable_baselines3.common.utils import polyak_update, update_learning_rate
from torch.nn import functional as F

from sb3_cql.common.offline import OfflineSAC, behaviour_cloning_loss
from sb3_cql.common.settings import check_count, check_finite, check_non_negative, finite_loss_value
from sb3_cql.cql.policies import FROM_SAC, CnnPolicy, CQLActor, CQLCritic, MlpPolicy, MultiInputPolicy

if TYPE_CHECKING:
    from minari import MinariDataset

#: Bound of the learned Lagrange multiplier, as in the reference implementation.
MAX_ALPHA_PRIME = 1e6


class CQL(OfflineSAC):
    """Conservative Q-Learning, CQL(H) (Kumar et al. 2020, https://arxiv.org/abs/2006.04779), trained offline.

    :meth:`train` is SAC's with one more critic loss term: for each critic,

    ``cql_alpha * (T * logsumexp_a(Q(s, a) / T) - Q(s, a_data))``

    beside its full TD loss (the critics' mean squared errors summed, at the reference implementations' relative
    weights), where the log-sum-exp runs over ``cql_n_actions`` uniform actions, ``cql_n_actions`` current-policy actions at
    ``s`` and ``cql_n_actions`` policy actions at ``s'`` (all scored at ``s``), importance-weighted by their
    densities, and ``T`` is ``cql_temperature``. With ``cql_target_action_gap`` set, the term becomes
    ``alpha' * cql_alpha * (gap - cql_target_action_gap)`` with the multiplier ``alpha'`` learned by dual gradient
    ascent (tinkoff-ai/CORL's form).

    Datasets, ``n_steps``, action chunks, the observation normaliser, online fine-tuning (``online_fraction``), the
    checks of every setting and atomic saves are the offline base's (:class:`~sb3_cql.common.OfflineSAC`). Defaults are
    the reference implementation's (tinkoff-ai/CORL's ``cql.py``: batch 256, critic learning rate 3e-4, actor learning
    rate 3e-5, tau 5e-3, ``cql_alpha`` 10, 10 sampled actions, a learned entropy coefficient, no entropy in the backup,
    no warm start); the thesis's grasping settings are in ``hyperparams/cql.yml``.

    :param policy: the policy model (``"MlpPolicy"``, ``"CnnPolicy"``, ``"MultiInputPolicy"``: SAC's, with CQL's
        actor and critic passes, :mod:`sb3_cql.cql.policies`).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id (a missing standard one is collected first), or a filled
        ``ReplayBuffer``; ``None`` for an empty buffer of ``buffer_size``.
    :param actor_learning_rate: learning rate of the actor; ``None`` for ``learning_rate`` (the critics', the entropy
        coefficient's and the Lagrange multiplier's).
    :param cql_alpha: weight of each critic's conservative gap against its full TD loss (its mean squared error), as
        tinkoff-ai/CORL's ``cql_alpha`` and the CQL paper's code weigh it (d3rlpy's ``conservative_weight`` multiplies
        the critics' mean gap, so its ``w`` is ``w / 2`` here with two critics). The default, 10, is CORL's, and trains
        as the thesis's 5 did against SAC's halved TD loss. ``0`` drops the term, not the rest: it is SAC with the
        deterministic backup (on by default), the imitation anchor and the reward shaping still applied, where set;
        SAC's own update also needs ``cql_deterministic_backup=False``, ``actor_bc_weight=0`` and no reward shaping.
    :param cql_n_actions: actions sampled per state for each of the three log-sum-exp groups.
    :param cql_temperature: temperature ``T`` of the log-sum-exp.
    :param cql_target_action_gap: with a value, learn a Lagrange multiplier ``alpha'`` that keeps the conservative gap
        near it: the term becomes ``alpha' * cql_alpha * (gap - cql_target_action_gap)`` per critic, as CORL's.
    :param cql_deterministic_backup: drop the entropy term from the TD target (as d3rlpy and the CQL paper's code).
    :param cql_max_backup: back up the max over ``cql_n_actions`` next-state policy actions instead of one sample.
    :param bc_steps: gradient steps at the start of training (counted across ``learn`` calls and ``save``/``load``)
        whose actor loss is behaviour cloning in place of the Q-value (the deterministic action fitted to the data
        actions by least squares), next to the entropy term, which sets the spread alone (through the log-std head);
        the critics train as usual meanwhile.
    :param bc_learning_rate: the actor's learning rate at the start of the warm start, decaying linearly over
        ``bc_steps`` to ``actor_learning_rate`` (imitation needs a larger rate than following Q, and a clone settles
        only as its rate decays); ``None`` for ``actor_learning_rate`` throughout.
    :param actor_bc_weight: after the warm start, keep imitating in the actor loss: SAC's actor loss (its entropy
        term too, :meth:`anchor_actor_loss`) divided by the batch's mean ``|Q|`` (detached) plus ``actor_bc_weight``
        times the warm start's behaviour-cloning loss, as in TD3+BC (Fujimoto & Gu 2021,
        https://arxiv.org/abs/2106.06860), whose ``alpha`` is ``1 / actor_bc_weight`` (its default 2.5 is 0.4 here).
        ``0`` (the default) is CQL's actor loss as defined (``docs/cql.md`` says what it does on the Panda data).
    :param kwargs: the offline base's keywords (:class:`~sb3_cql.common.OfflineSAC`: ``learning_rate``,
        ``buffer_size``, ``normalize_observations``, ``online_fraction``, ``online_buffer_size``, ``learning_starts``,
        ``deterministic_rollouts``, ``action_chunk``, ``best_of_n``, ``best_of_n_scale``, ``reward_scale``,
        ``reward_bias``, ``policy_kwargs``) and SAC's (``batch_size``, ``tau``, ``gamma``, ``ent_coef``,
        ``target_entropy``, ``target_update_interval``, ``train_freq``, ``gradient_steps``, ``action_noise``,
        ``replay_buffer_class``, ``replay_buffer_kwargs``, ``n_steps``, ``stats_window_size``, ``tensorboard_log``,
        ``verbose``, ``seed``, ``device``). With a sparse 0/1 reward, a negative ``reward_bias`` (the thesis's code:
        ``reward_scale`` 4, ``reward_bias`` -2) gives every step that does not reach the goal a cost, and puts the
        Q-values on the scale of ``cql_target_action_gap``.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy_from_sac: ClassVar[dict[type[BasePolicy], type[BasePolicy]]] = FROM_SAC

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str,
        dataset: MinariDataset | str | ReplayBuffer | None = None,
        actor_learning_rate: float | Schedule | None = 3e-5,
        cql_alpha: float = 10.0,
        cql_n_actions: int = 10,
        cql_temperature: float = 1.0,
        cql_target_action_gap: float | None = None,
        cql_deterministic_backup: bool = True,
        cql_max_backup: bool = False,
        bc_steps: int = 0,
        bc_learning_rate: float | None = None,
        actor_bc_weight: float = 0.0,
        **kwargs: Any,
    ) -> None:
        self.cql_alpha = cql_alpha
        self.cql_n_actions = cql_n_actions
        self.cql_temperature = cql_temperature
        self.cql_target_action_gap = cql_target_action_gap
        self.cql_deterministic_backup = cql_deterministic_backup
        self.cql_max_backup = cql_max_backup
        self.bc_steps = bc_steps
        self.bc_learning_rate = bc_learning_rate
        self.actor_bc_weight = actor_bc_weight
        self.log_alpha_prime: th.Tensor | None = None
        self.alpha_prime_optimizer: th.optim.Adam | None = None
        super().__init__(policy, env, dataset, actor_learning_rate=actor_learning_rate, **kwargs)

    def _check_settings(self) -> None:
        """OfflineSAC's checks, and those of CQL's own settings."""
        super()._check_settings()
        check_count("bc_steps", self.bc_steps, 0)
        check_count("cql_n_actions", self.cql_n_actions, 1)
        check_non_negative([("cql_alpha", self.cql_alpha), ("actor_bc_weight", self.actor_bc_weight)])
        check_non_negative([("cql_temperature", self.cql_temperature)], strictly=True)
        if self.cql_target_action_gap is not None:
            check_finite([("cql_target_action_gap", self.cql_target_action_gap)])
        if self.bc_learning_rate is not None:
            check_non_negative([("bc_learning_rate", self.bc_learning_rate)], strictly=True)

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.cql_target_action_gap is not None:
            self.log_alpha_prime = th.zeros(1, device=self.device, requires_grad=True)
            self.alpha_prime_optimizer = th.optim.Adam([self.log_alpha_prime], lr=self.lr_schedule(1))

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SAC's ``train()`` with the conservative term added to the critic loss. Each variant of the update is one
        hook, overridable by a subclass: :meth:`compute_target` (SB3's n-step ``discounts``, the critics' rewards,
        :meth:`next_state_values` with the max backup), :meth:`td_loss`, :meth:`conservative_gaps` (Cal-QL's bound in
        :meth:`policy_values_in_logsumexp`), :meth:`conservative_loss` (with the Lagrange multiplier, whose dual step
        is :meth:`update_alpha_prime`), :meth:`check_critic_loss` (divergence) and :meth:`compute_actor_loss` (SAC's,
        or the warm start's :meth:`warm_start_actor_loss`, with the imitation anchor of :meth:`anchor_actor_loss`).
        One critic pass (:meth:`q_values_at_data_and_sampled_actions`) scores the data actions, for the TD loss and
        the conservative term, and the sampled actions of :meth:`sample_conservative_actions`, for the term."""
        self.policy.set_training_mode(True)
        optimizers = [self.critic.optimizer]
        optimizers += [opt for opt in (self.ent_coef_optimizer, self.alpha_prime_optimizer) if opt is not None]
        self._update_learning_rate(optimizers)
        actor_learning_rate = self._actor_learning_rate()
        update_learning_rate(self.actor.optimizer, actor_learning_rate)
        self.logger.record("train/actor_learning_rate", actor_learning_rate)
        logs: dict[str, list[float]] = {}

        for _ in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            # For n-step replay, the discount of the bootstrap is gamma ** (steps summed), as SAC's.
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma

            # The actor runs once on s and once on s' per step; every sample below is drawn from these parameters
            # (the actor changes only at the end of the step).
            policy = self.actor.get_action_dist_params(replay_data.observations)[:2]
            actions_pi, log_prob = self.actor.action_dist.log_prob_from_params(*policy)
            log_prob = log_prob.reshape(-1, 1)
            with th.no_grad():
                next_policy = self.actor.get_action_dist_params(replay_data.next_observations)[:2]

            ent_coef_loss = None
            if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
                ent_coef = th.exp(self.log_ent_coef.detach())
                ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
                _append(logs, "train/ent_coef_loss", ent_coef_loss.item())
            else:
                ent_coef = self.ent_coef_tensor
            _append(logs, "train/ent_coef", ent_coef.item())

            with th.no_grad():
                target_q_values = self.compute_target(replay_data, next_policy, ent_coef, discounts)

            detached_policy = (policy[0].detach(), policy[1].detach())
            sampled_actions, log_densities = self.sample_conservative_actions(replay_data, detached_policy, next_policy)
            q_data, q_sampled = self.q_values_at_data_and_sampled_actions(replay_data, sampled_actions)
            td_loss = self.td_loss(q_data, target_q_values)
            gaps = self.conservative_gaps(q_data, q_sampled, log_densities, replay_data, logs)
            conservative_loss = self.conservative_loss(gaps)
            if self.alpha_prime_optimizer is not None:  # after the loss took alpha' as it was, as CORL's
                self.update_alpha_prime(gaps, logs)
            critic_loss = td_loss + conservative_loss
            critic_loss_value = self.check_critic_loss(critic_loss)
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()

            actor_loss = self.compute_actor_loss(replay_data, policy, actions_pi, log_prob, ent_coef, logs)
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()

            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

            _append(logs, "train/critic_loss", critic_loss_value)
            _append(logs, "train/actor_loss", actor_loss.item())
            _append(logs, "train/cql_td_loss", td_loss.item())
            _append(logs, "train/cql_loss", conservative_loss.item())

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(key, float(np.mean(values)))

    # The TD target.

    def compute_target(
        self,
        replay_data: ReplayBufferSamples,
        next_policy: tuple[th.Tensor, th.Tensor],
        ent_coef: th.Tensor,
        discounts: th.Tensor | float,
    ) -> th.Tensor:
        """SAC's TD target, ``rewards + (1 - dones) * discounts * V(s')``, with the critics' rewards
        (:meth:`critic_rewards`) and :meth:`next_state_values`. ``discounts`` are the samples' (SB3's n-step returns)
        or ``gamma``.

        :param replay_data: the batch.
        :param next_policy: the actor's (mean actions, log-std) at the batch's next observations.
        :param ent_coef: SAC's entropy coefficient.
        :param discounts: the discount of each sample's bootstrap.
        """
        next_q_values = self.next_state_values(replay_data.next_observations, next_policy, ent_coef)
        return self.critic_rewards(replay_data) + (1 - replay_data.dones) * discounts * next_q_values

    def next_state_values(
        self, next_observations: th.Tensor, next_policy: tuple[th.Tensor, th.Tensor], ent_coef: th.Tensor
    ) -> th.Tensor:
        """The soft (or, with ``cql_deterministic_backup``, plain) value of the next states under the target critics,
        for a policy sample (or, with ``cql_max_backup``, the best of ``cql_n_actions``) from ``next_policy``'s
        (mean actions, log-std)."""
        n_samples = self.cql_n_actions if self.cql_max_backup else 1
        next_actions, next_log_prob = self.sample_policy_actions(*next_policy, n_samples)
        if n_samples > 1:
            next_observations = _map(lambda tensor: tensor.repeat_interleave(n_samples, dim=0), next_observations)
        next_q_values = th.cat(self.critic_target(next_observations, next_actions), dim=1)
        next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
        if not self.cql_deterministic_backup:
            next_q_values = next_q_values - ent_coef * next_log_prob.reshape(-1, 1)
        if n_samples > 1:
            next_q_values = next_q_values.reshape(-1, n_samples).max(dim=1, keepdim=True).values
        return next_q_values

    # The conservative term.

    def sample_conservative_actions(
        self,
        replay_data: ReplayBufferSamples,
        policy: tuple[th.Tensor, th.Tensor],
        next_policy: tuple[th.Tensor, th.Tensor],
    ) -> tuple[th.Tensor, th.Tensor]:
        """The actions the log-sum-exp runs over and their log-densities, drawn without gradients: ``cql_n_actions``
        per state of each of three groups, uniform on [-1, 1], the policy's at s and the policy's at s' (from the
        (mean actions, log-std) ``policy`` and ``next_policy``). The actions are ``(3 * batch * cql_n_actions,
        action_dim)``, group by group and state-major within a group; the log-densities ``(batch, 3 * cql_n_actions)``,
        a state's row holding its groups side by side (the uniform density ``(1/2)^|A|``, the policy's own)."""
        batch_size, n = replay_data.actions.shape[0], self.cql_n_actions
        action_dim = replay_data.actions.shape[1]  # the action's, or with action_chunk the whole chunk's
        with th.no_grad():
            random_actions = th.empty(batch_size * n, action_dim, device=self.device).uniform_(-1.0, 1.0)
            policy_actions, policy_log_prob = self.sample_policy_actions(*policy, n)
            next_policy_actions, next_policy_log_prob = self.sample_policy_actions(*next_policy, n)
        actions = th.cat([random_actions, policy_actions, next_policy_actions])
        log_densities = th.cat(
            [
                th.full((batch_size, n), action_dim * math.log(0.5), device=self.device),
                policy_log_prob.reshape(batch_size, n),
                next_policy_log_prob.reshape(batch_size, n),
            ],
            dim=1,
        )
        return actions, log_densities

    def q_values_at_data_and_sampled_actions(
        self, replay_data: ReplayBufferSamples, sampled_actions: th.Tensor
    ) -> tuple[list[th.Tensor], th.Tensor]:
        """Each critic's Q at the data actions (a ``(batch, 1)`` tensor a critic) and at the ``sampled_actions`` of
        :meth:`sample_conservative_actions` (all critics' in one ``(n_critics, 3, batch, cql_n_actions)`` tensor), from
        one critic pass (:meth:`~sb3_cql.cql.policies.CQLCritic.forward_fused`) over the data's states and each state
        ``3 * cql_n_actions`` times."""
        batch_size, n = replay_data.actions.shape[0], self.cql_n_actions
        # The data's states, then each state n times for each of the three groups (observations of any shape).
        all_observations = _map(
            lambda tensor: th.cat([tensor, tensor.repeat_interleave(n, dim=0).repeat(3, *[1] * (tensor.dim() - 1))]),
            replay_data.observations,
        )
        actions = th.cat([replay_data.actions, sampled_actions])
        # CQLCritic's fused pass, also on SAC's own critic (a policy class of the user's may build it).
        forward_fused = getattr(self.critic, "forward_fused", None)
        forward_fused = forward_fused or functools.partial(CQLCritic.forward_fused, self.critic)
        q_values = forward_fused(all_observations, actions)
        q_data = [critic_q[:batch_size] for critic_q in q_values]
        q_sampled = th.stack([critic_q[batch_size:].reshape(3, batch_size, n) for critic_q in q_values])
        return q_data, q_sampled

    def conservative_gaps(
        self,
        q_data: list[th.Tensor],
        q_sampled: th.Tensor,
        log_densities: th.Tensor,
        replay_data: ReplayBufferSamples,
        logs: dict[str, list[float]],
    ) -> list[th.Tensor]:
        """Each critic's gap ``mean(T * logsumexp_a(Q(s, a) / T) - Q(s, a_data))``, the log-sum-exp over the sampled
        actions importance-weighted by their ``log_densities``, from the Q-values of
        :meth:`q_values_at_data_and_sampled_actions`; the policy groups' values go through
        :meth:`policy_values_in_logsumexp`. Logs ``train/cql_q_*`` and ``train/cql_gap`` (the first critic's)."""
        q_policy = self.policy_values_in_logsumexp(q_sampled[:, 1:], replay_data, logs)
        gaps = []
        for critic_q_data, q_random, critic_q_policy in zip(q_data, q_sampled[:, 0], q_policy, strict=True):
            importance_weighted = th.cat([q_random, *critic_q_policy], dim=1) - log_densities
            logsumexp = th.logsumexp(importance_weighted / self.cql_temperature, dim=1) * self.cql_temperature
            gaps.append(logsumexp.mean() - critic_q_data.mean())
        _append(logs, "train/cql_q_data", q_data[0].mean().item())
        _append(logs, "train/cql_q_random", q_sampled[0, 0].mean().item())
        _append(logs, "train/cql_q_policy", q_sampled[0, 1].mean().item())
        _append(logs, "train/cql_q_next_policy", q_sampled[0, 2].mean().item())
        _append(logs, "train/cql_gap", gaps[0].item())
        return gaps

    def policy_values_in_logsumexp(
        self, q_policy: th.Tensor, replay_data: ReplayBufferSamples, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """The values of the policy's actions as the log-sum-exp takes them: CQL's, as the critics give them.
        :class:`~sb3_cql.cql.CalQL` bounds them below by the return-to-go.

        :param q_policy: every critic's Q at the policy's actions at s and at s', ``(n_critics, 2, batch,
            cql_n_actions)``.
        :param replay_data: the batch.
        :param logs: the step's logs.
        """
        return q_policy

    def td_loss(self, q_data: list[th.Tensor], target_q_values: th.Tensor) -> th.Tensor:
        """The TD loss of the critics, from each critic's Q at the data actions: each one's mean squared error to the
        target, summed over the critics, as the reference implementations weigh it against the conservative term
        (tinkoff-ai/CORL's ``qf1_loss + qf2_loss``, the CQL paper's code). (SAC's own ``0.5 * sum`` would halve the TD
        loss beside the conservative term, and so double what ``cql_alpha`` means.)"""
        return sum(F.mse_loss(current_q, target_q_values) for current_q in q_data)

    def alpha_prime(self) -> th.Tensor:
        """The Lagrange multiplier ``alpha' = clamp(exp(log_alpha_prime), 0, 1e6)``, as tinkoff-ai/CORL's."""
        assert self.log_alpha_prime is not None
        return self.log_alpha_prime.exp().clamp(0.0, MAX_ALPHA_PRIME)

    def conservative_loss(self, gaps: list[th.Tensor]) -> th.Tensor:
        """The term added to the TD loss: ``cql_alpha`` times each critic's gap, summed over the critics; with
        ``cql_target_action_gap``, tinkoff-ai/CORL's Lagrangian ``alpha' * cql_alpha * (gap - cql_target_action_gap)``
        per critic, with ``alpha'`` (:meth:`alpha_prime`, detached) as it is before this step's dual update
        (:meth:`update_alpha_prime`, which :meth:`train` makes after it)."""
        if self.log_alpha_prime is None:
            return sum(self.cql_alpha * gap for gap in gaps)
        alpha_prime = self.alpha_prime().detach()
        return sum(alpha_prime * self.cql_alpha * (gap - self.cql_target_action_gap) for gap in gaps)

    def update_alpha_prime(self, gaps: list[th.Tensor], logs: dict[str, list[float]]) -> None:
        """One dual step on the Lagrange multiplier (:meth:`alpha_prime`): Adam on ``-0.5 * sum(alpha' * cql_alpha *
        (gap - cql_target_action_gap))`` over the critics (the gaps detached), so ``alpha'`` grows while the gaps
        exceed the target and shrinks below it, as tinkoff-ai/CORL's. Logs ``train/cql_alpha_prime`` (before the
        step) and ``train/cql_alpha_prime_loss``."""
        assert self.log_alpha_prime is not None and self.alpha_prime_optimizer is not None
        alpha_prime = self.alpha_prime()
        excess = [self.cql_alpha * (gap.detach() - self.cql_target_action_gap) for gap in gaps]
        alpha_prime_loss = -0.5 * sum(alpha_prime * term for term in excess)
        self.alpha_prime_optimizer.zero_grad()
        alpha_prime_loss.backward()
        self.alpha_prime_optimizer.step()
        _append(logs, "train/cql_alpha_prime", alpha_prime.item())
        _append(logs, "train/cql_alpha_prime_loss", alpha_prime_loss.item())

    def check_critic_loss(self, critic_loss: th.Tensor) -> float:
        """The critic loss as a number; :class:`TrainingDivergedError` if it is NaN or infinite."""
        hint = "try a lower learning_rate, reward scaling or cql_target_action_gap"
        return finite_loss_value(critic_loss, "CQL's critic loss", self.num_timesteps + 1, hint)

    # The actor loss.

    def compute_actor_loss(
        self,
        replay_data: ReplayBufferSamples,
        policy: tuple[th.Tensor, th.Tensor],
        actions_pi: th.Tensor,
        log_prob: th.Tensor,
        ent_coef: th.Tensor,
        logs: dict[str, list[float]],
    ) -> th.Tensor:
        """SAC's actor loss, ``ent_coef * log_prob - min Q(s, a_pi)``, with the anchor of :meth:`anchor_actor_loss`;
        during the warm start (:meth:`in_warm_start`) :meth:`warm_start_actor_loss` instead.

        :param replay_data: the batch.
        :param policy: the actor's (mean actions, log-std) at the batch's observations.
        :param actions_pi: the actor's sampled actions there, ``log_prob`` their log-densities.
        :param ent_coef: SAC's entropy coefficient.
        :param logs: the step's logs.
        """
        if self.in_warm_start():
            return self.warm_start_actor_loss(replay_data, ent_coef)
        q_values_pi = th.cat(self.critic(replay_data.observations, actions_pi), dim=1)
        min_qf_pi, _ = th.min(q_values_pi, dim=1, keepdim=True)
        actor_loss = (ent_coef * log_prob - min_qf_pi).mean()
        return self.anchor_actor_loss(actor_loss, min_qf_pi, policy[0], replay_data, logs)

    def warm_start_actor_loss(self, replay_data: ReplayBufferSamples, ent_coef: th.Tensor) -> th.Tensor:
        """The behaviour-cloning warm start's actor loss: in SAC's, imitation in place of Q."""
        # The deterministic action is fitted by least squares (as sb3_cql.BC: the mean of a tanh-Gaussian fitted by
        # likelihood is biased when data actions saturate at +-1, as the gripper's do); the spread is SAC's, set by
        # the entropy term against the target entropy, and trains the log-std head only: through the shared layers it
        # moved the mean enough to break a working grasp within a few hundred steps. (A likelihood of the data actions
        # for the spread made the policy's samples bang-bang on the noisy data, whose clipped actions often sit at
        # +-1; the conservative term then kept Q at the policy's samples tens below Q at the data actions, and the
        # backup carried that gap into every Q-value: docs/findings.md.)
        # CQLActor's pass, also on SAC's own actor (a policy class of the user's may build it).
        imitation_dist_params = getattr(self.actor, "imitation_dist_params", None)
        imitation_dist_params = imitation_dist_params or functools.partial(CQLActor.imitation_dist_params, self.actor)
        mean_actions, log_std = imitation_dist_params(replay_data.observations)
        _, spread_log_prob = self.actor.action_dist.log_prob_from_params(mean_actions.detach(), log_std)
        return (ent_coef * spread_log_prob).mean() + behaviour_cloning_loss(mean_actions, replay_data.actions)

    def anchor_actor_loss(
        self,
        actor_loss: th.Tensor,
        min_qf_pi: th.Tensor,
        mean_actions: th.Tensor,
        replay_data: ReplayBufferSamples,
        logs: dict[str, list[float]],
    ) -> th.Tensor:
        """With ``actor_bc_weight``, TD3+BC's anchor on SAC's whole ``actor_loss`` (``mean(ent_coef * log_prob - Q)``):
        divided by the batch's mean ``|Q|`` (detached: on a scale of 1 whatever the rewards), plus ``actor_bc_weight``
        times the imitation of the data by the actor's ``mean_actions``; ``actor_loss`` unchanged without it.

        The entropy term is divided too, unlike a Q-only normalisation (TD3+BC's actor has no entropy term): with
        ``|Q|`` in the hundreds it then barely pulls, and the clone's spread and saturated gripper commands stay as the
        warm start left them. Dividing Q alone, the shipped Panda configuration lost the clone within 1,000 steps of
        the warm start's end (the documentation's *What we learned*, *The anchor must scale the entropy term too*)."""
        if self.actor_bc_weight <= 0:
            return actor_loss
        bc_loss = behaviour_cloning_loss(mean_actions, replay_data.actions)
        _append(logs, "train/actor_bc_loss", bc_loss.item())
        return actor_loss / min_qf_pi.abs().mean().detach() + self.actor_bc_weight * bc_loss

    def in_warm_start(self) -> bool:
        """Whether the next gradient step is one of the first ``bc_steps`` of the model's training. Counted in gradient
        steps made (``_n_updates``, saved with the model), not ``num_timesteps``: RL-Zoo3 continues a saved model
        (``-i``) with the count of timesteps restarted at 0."""
        return self._n_updates < self.bc_steps

    def _actor_learning_rate(self) -> float:
        """The actor's schedule, or during the warm start the linear decay from ``bc_learning_rate`` to it."""
        learning_rate = self.actor_lr_schedule(self._current_progress_remaining)
        if self.bc_learning_rate is None or not self.in_warm_start():
            return learning_rate
        fraction = self._n_updates / self.bc_steps
        return self.bc_learning_rate + fraction * (learning_rate - self.bc_learning_rate)

    def sample_policy_actions(self, mean_actions: th.Tensor, log_std: th.Tensor, n: int) -> tuple[th.Tensor, th.Tensor]:
        """``n`` actions per state (state-major order) of the policy whose ``get_action_dist_params`` gave
        ``mean_actions`` and ``log_std``, and their log-densities.

        Only the sampling is repeated: the same distribution as running the actor on ``n`` copies of each state, at
        a fraction of the cost. (CQL has no gSDE.)
        """
        mean_actions, log_std = mean_actions.repeat_interleave(n, dim=0), log_std.repeat_interleave(n, dim=0)
        return self.actor.action_dist.log_prob_from_params(mean_actions, log_std)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        if self.alpha_prime_optimizer is not None:
            state_dicts.append("alpha_prime_optimizer")
            variables.append("log_alpha_prime")
        return state_dicts, variables


def _map(function: Any, observations: th.Tensor | dict[str, th.Tensor]) -> th.Tensor | dict[str, th.Tensor]:
    """``function`` applied to a batch of observations, or to each of Dict observations."""
    if isinstance(observations, dict):
        return {key: function(tensor) for key, tensor in observations.items()}
    return function(observations)


def _append(logs: dict[str, list[float]], key: str, value: float) -> None:
    logs.setdefault(key, []).append(value)
