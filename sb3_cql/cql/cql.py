"""Conservative Q-Learning (CQL(H)) for offline RL: SAC plus a conservative term in the critic loss."""

from __future__ import annotations

import functools
import math
import warnings
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, ReplayBufferSamples, Schedule
from stable_baselines3.common.utils import polyak_update, update_learning_rate
from torch.nn import functional as F

from sb3_cql.common.offline import OfflineSAC, behaviour_cloning_loss, frozen
from sb3_cql.common.policies import map_observations
from sb3_cql.common.settings import check_count, check_finite, check_non_negative, finite_loss_value
from sb3_cql.cql.policies import FROM_SAC, CnnPolicy, CQLActor, CQLCritic, MlpPolicy, MultiInputPolicy

if TYPE_CHECKING:
    from minari import MinariDataset

#: Bound of the learned Lagrange multiplier, as in the reference implementation.
MAX_ALPHA_PRIME = 1e6


class CQL(OfflineSAC):
    """Conservative Q-Learning, CQL(H) (Kumar et al. 2020, https://arxiv.org/abs/2006.04779), trained offline.

    :meth:`train` is SAC's with, for each critic, the term ``cql_alpha * (T * logsumexp_a(Q(s, a) / T) - Q(s, a_data))``
    beside its full TD loss, the log-sum-exp over ``cql_n_actions`` uniform actions, current-policy actions at ``s``
    and policy actions at ``s'`` (all scored at ``s``, importance-weighted by their densities), ``T`` the
    ``cql_temperature``. With ``cql_target_action_gap`` the term is ``alpha' * cql_alpha * (gap -
    cql_target_action_gap)``, ``alpha'`` learned by dual gradient ascent (tinkoff-ai/CORL's form). Everything else is
    the offline base's (:class:`~sb3_cql.common.OfflineSAC`). The defaults learn the weight (``cql_alpha`` 5 towards a
    gap of 10, the multiplier at a rate of 1e-4: d3rlpy's ``CQLConfig``'s); the rest are tinkoff-ai/CORL's ``cql.py``'s.
    They were chosen across the data sets of ``benchmarks/offline_suite.py``, where the fixed weight of 10 failed a
    sparse task's mixed data and a multiplier at the critics' rate a dense one's; the
    thesis's grasping settings, a fixed weight among them, are in ``hyperparams/cql.yml``.

    :param policy: ``"MlpPolicy"``, ``"CnnPolicy"`` or ``"MultiInputPolicy"`` (SAC's, with CQL's actor and critic
        passes, :mod:`sb3_cql.cql.policies`).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id (a missing standard one is collected first), or a filled
        ``ReplayBuffer``; ``None`` for an empty buffer of ``buffer_size``.
    :param actor_learning_rate: the actor's learning rate; ``None`` for ``learning_rate`` (the critics' and the entropy
        coefficient's).
    :param cql_alpha: weight of each critic's conservative gap against its full TD loss, as CORL's ``cql_alpha`` and
        d3rlpy's ``conservative_weight``; with ``cql_target_action_gap`` it is scaled by the learned ``alpha'``. ``0``
        drops the term (in either form) only: SAC's own update also needs ``cql_deterministic_backup=False``,
        ``actor_bc_weight=0`` and no reward shaping.
    :param cql_n_actions: actions sampled per state for each of the three log-sum-exp groups.
    :param cql_temperature: temperature ``T`` of the log-sum-exp.
    :param cql_target_action_gap: learn the Lagrange multiplier ``alpha'`` (from 1, at ``cql_alpha_learning_rate``) that
        eases the term while the gap is under this value and strengthens it above (d3rlpy's ``alpha_threshold``);
        ``None`` for a fixed weight ``cql_alpha``. Given to ``load``, either form continues a model saved with the
        other (a multiplier the save lacks starts at 1).
    :param cql_alpha_learning_rate: Adam's learning rate for ``log(alpha')`` (d3rlpy's ``alpha_learning_rate``): at
        1e-4 the weight eases at most to about e^-1 of its start in 10,000 steps; ``None`` for ``learning_rate``, the
        critics' (CORL's, and the default until 2026-12-07, which eased too far on a dense mixture of good episodes and
        noise).
    :param cql_deterministic_backup: drop the entropy term from the TD target (as d3rlpy and the CQL paper's code).
    :param cql_max_backup: back up the max over ``cql_n_actions`` next-state policy actions instead of one sample.
    :param bc_steps: first gradient steps (counted across ``learn`` calls and ``save``/``load``) whose actor loss is
        behaviour cloning in place of the Q-value (:meth:`warm_start_actor_loss`); the critics train as usual.
    :param bc_learning_rate: the actor's learning rate at the start of the warm start, decaying linearly over
        ``bc_steps`` to ``actor_learning_rate``; ``None`` for ``actor_learning_rate`` throughout.
    :param actor_bc_weight: after the warm start, TD3+BC's anchor (Fujimoto & Gu 2021,
        https://arxiv.org/abs/2106.06860, whose ``alpha`` is ``1 / actor_bc_weight``) on the actor loss
        (:meth:`anchor_actor_loss`); ``0``: CQL's actor loss as defined.
    :param kwargs: the offline base's keywords (:class:`~sb3_cql.common.OfflineSAC`) and SAC's. With a sparse 0/1
        reward, a negative ``reward_bias`` (the thesis's: ``reward_scale`` 4, ``reward_bias`` -2) puts the Q-values
        on the scale of ``cql_target_action_gap``.
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
        cql_alpha: float = 5.0,
        cql_n_actions: int = 10,
        cql_temperature: float = 1.0,
        cql_target_action_gap: float | None = 10.0,
        cql_alpha_learning_rate: float | None = 1e-4,
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
        self.cql_alpha_learning_rate = cql_alpha_learning_rate
        self.cql_deterministic_backup = cql_deterministic_backup
        self.cql_max_backup = cql_max_backup
        self.bc_steps = bc_steps
        self.bc_learning_rate = bc_learning_rate
        self.actor_bc_weight = actor_bc_weight
        self.log_alpha_prime: th.Tensor | None = None
        #: Adam on ``log_alpha_prime`` where ``cql_target_action_gap`` is set; ``None`` for a fixed ``cql_alpha``.
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
        if self.cql_alpha_learning_rate is not None:
            check_non_negative([("cql_alpha_learning_rate", self.cql_alpha_learning_rate)], strictly=True)

    def _setup_model(self) -> None:
        super()._setup_model()
        # alpha' = 1 at the start; the tensor exists with a fixed weight too, so that a model saved with a multiplier
        # loads with ``cql_target_action_gap=None`` (SB3's load sets the saved tensor's data in place).
        self.log_alpha_prime = th.zeros(1, device=self.device, requires_grad=True)
        if self.cql_target_action_gap is not None:
            self.alpha_prime_optimizer = th.optim.Adam([self.log_alpha_prime], lr=self._alpha_prime_learning_rate())

    def _fill_from_dataset(self, dataset: MinariDataset | str | ReplayBuffer) -> None:
        """The offline base's, then a warning where the settings are ones seen to fail on data like these
        (:meth:`warn_of_settings_known_to_fail`)."""
        super()._fill_from_dataset(dataset)
        self.warn_of_settings_known_to_fail()

    def warn_of_settings_known_to_fail(self) -> None:
        """Warn, on one line, of a fixed ``cql_alpha`` of 10 or more without an anchor (``actor_bc_weight`` 0) on data
        whose reward is sparse (:func:`rare_reward_share`): on the offline suite's sparse MountainCarContinuous-v0
        mixture that setting never reached the goal, where the default learned weight always did."""
        if self.alpha_prime_optimizer is not None or self.cql_alpha < 10.0 or self.actor_bc_weight > 0.0:
            return
        assert self.replay_buffer is not None
        share = rare_reward_share(self.replay_buffer.rewards[: self.replay_buffer.size()])
        if share is not None:
            warnings.warn(
                f"CQL with a fixed cql_alpha={self.cql_alpha:g} and no anchor on a sparse reward ({share:.2%} of the "
                "transitions carry it) failed such data where the learned weight succeeded; leave "
                "cql_target_action_gap at its default 10, or anchor the actor (actor_bc_weight); docs: cql.md, Defaults",
                UserWarning,
                stacklevel=2,
            )

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SAC's ``train()`` with the conservative term added to the critic loss, each variant of the update one
        overridable hook: :meth:`compute_target`, :meth:`td_loss`, :meth:`conservative_gaps`,
        :meth:`conservative_loss` (and :meth:`update_alpha_prime`), :meth:`check_critic_loss` and
        :meth:`compute_actor_loss`. One critic pass (:meth:`q_values_at_data_and_sampled_actions`) scores the data's
        and the sampled actions."""
        self.policy.set_training_mode(True)
        optimizers = [self.critic.optimizer]
        optimizers += [self.ent_coef_optimizer] if self.ent_coef_optimizer is not None else []
        self._update_learning_rate(optimizers)
        if self.alpha_prime_optimizer is not None:
            update_learning_rate(self.alpha_prime_optimizer, self._alpha_prime_learning_rate())
        actor_learning_rate = self._actor_learning_rate()
        update_learning_rate(self.actor.optimizer, actor_learning_rate)
        self.logger.record("train/actor_learning_rate", actor_learning_rate)
        logs: dict[str, list[float]] = {}

        for _ in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma

            # The actor runs once on s and once on s'; every sample below is drawn from these parameters.
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
        """SAC's TD target, ``rewards + (1 - dones) * discounts * V(s')``, with :meth:`critic_rewards` and
        :meth:`next_state_values` at ``next_policy``, the actor's (mean actions, log-std) at the next observations;
        ``discounts`` are the samples' (n-step returns) or ``gamma``."""
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
            next_observations = map_observations(lambda tensor: tensor.repeat_interleave(n_samples, dim=0), next_observations)
        next_q_values = th.cat(self.critic_target(next_observations, next_actions), dim=1)
        next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
        if not self.cql_deterministic_backup:
            next_q_values = next_q_values - ent_coef * next_log_prob.reshape(-1, 1)
        if n_samples > 1:
            next_q_values = next_q_values.reshape(-1, n_samples).max(dim=1, keepdim=True).values
        return next_q_values

    # The conservative term.

    def sample_conservative_actions(
        self, replay_data: ReplayBufferSamples, policy: tuple[th.Tensor, th.Tensor], next_policy: tuple[th.Tensor, th.Tensor]
    ) -> tuple[th.Tensor, th.Tensor]:
        """The log-sum-exp's actions and log-densities, drawn without gradients: ``cql_n_actions`` per state of each
        group (uniform on [-1, 1], the policy's at s, the policy's at s'), the actions ``(3 * batch * cql_n_actions,
        action_dim)`` group by group and state-major, the log-densities ``(batch, 3 * cql_n_actions)``."""
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
        """Each critic's Q at the data actions (``(batch, 1)`` a critic) and at the ``sampled_actions`` (all critics'
        ``(n_critics, 3, batch, cql_n_actions)``), from one pass of
        :meth:`~sb3_cql.cql.policies.CQLCritic.forward_fused`."""
        batch_size, n = replay_data.actions.shape[0], self.cql_n_actions
        all_observations = map_observations(
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
        """Each critic's gap ``mean(T * logsumexp_a(Q(s, a) / T) - Q(s, a_data))``, importance-weighted by
        ``log_densities``, the policy groups' values through :meth:`policy_values_in_logsumexp`. Logs
        ``train/cql_q_*`` and ``train/cql_gap`` (the first critic's)."""
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
        """The values ``q_policy`` (``(n_critics, 2, batch, cql_n_actions)``) of the policy's actions at s and s' as
        the log-sum-exp takes them: as they are; :class:`~sb3_cql.cql.CalQL` bounds them below."""
        return q_policy

    def td_loss(self, q_data: list[th.Tensor], target_q_values: th.Tensor) -> th.Tensor:
        """The critics' mean squared errors to the target, summed, as CORL's ``qf1_loss + qf2_loss`` (SAC's ``0.5 *
        sum`` would double what ``cql_alpha`` means)."""
        return sum(F.mse_loss(current_q, target_q_values) for current_q in q_data)

    def alpha_prime(self) -> th.Tensor:
        """The Lagrange multiplier ``alpha' = clamp(exp(log_alpha_prime), 0, 1e6)``, as tinkoff-ai/CORL's."""
        assert self.log_alpha_prime is not None
        return self.log_alpha_prime.exp().clamp(0.0, MAX_ALPHA_PRIME)

    def conservative_loss(self, gaps: list[th.Tensor]) -> th.Tensor:
        """``cql_alpha`` times each critic's gap, summed; with ``cql_target_action_gap``, ``alpha' * cql_alpha * (gap -
        cql_target_action_gap)`` per critic, ``alpha'`` detached and as before this step's :meth:`update_alpha_prime`."""
        if self.alpha_prime_optimizer is None:
            return sum(self.cql_alpha * gap for gap in gaps)
        alpha_prime = self.alpha_prime().detach()
        return sum(alpha_prime * self.cql_alpha * (gap - self.cql_target_action_gap) for gap in gaps)

    def update_alpha_prime(self, gaps: list[th.Tensor], logs: dict[str, list[float]]) -> None:
        """One Adam step of ``alpha'`` on ``-0.5 * sum(alpha' * cql_alpha * (gap - cql_target_action_gap))``, the gaps
        detached, as CORL's. Logs ``train/cql_alpha_prime`` (before the step) and ``train/cql_alpha_prime_loss``."""
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
        """SAC's actor loss, ``ent_coef * log_prob - min Q(s, a_pi)``, with :meth:`anchor_actor_loss`; during the warm
        start (:meth:`in_warm_start`) :meth:`warm_start_actor_loss`. ``policy`` is the actor's (mean actions,
        log-std) at the observations, ``actions_pi`` its samples, ``log_prob`` their log-densities."""
        if self.in_warm_start():
            return self.warm_start_actor_loss(replay_data, ent_coef)
        with frozen(self.critic) as critic:
            q_values_pi = th.cat(critic(replay_data.observations, actions_pi), dim=1)
        min_qf_pi, _ = th.min(q_values_pi, dim=1, keepdim=True)
        actor_loss = (ent_coef * log_prob - min_qf_pi).mean()
        return self.anchor_actor_loss(actor_loss, min_qf_pi, policy[0], replay_data, logs)

    def warm_start_actor_loss(self, replay_data: ReplayBufferSamples, ent_coef: th.Tensor) -> th.Tensor:
        """The warm start's actor loss: SAC's with imitation in place of Q. The deterministic action is fitted by
        least squares (as :class:`~sb3_cql.BC`); the spread is set by the entropy term and trains the log-std head
        only (through the shared layers it broke a working grasp; ``docs/findings.md``)."""
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
        """With ``actor_bc_weight``, TD3+BC's anchor: SAC's whole ``actor_loss``, entropy term included (see
        ``docs/findings.md``, *The anchor must scale the entropy term too*), divided by the batch's mean ``|Q|``
        (detached), plus ``actor_bc_weight`` times the imitation of the data by ``mean_actions``."""
        if self.actor_bc_weight <= 0:
            return actor_loss
        bc_loss = behaviour_cloning_loss(mean_actions, replay_data.actions)
        _append(logs, "train/actor_bc_loss", bc_loss.item())
        return actor_loss / min_qf_pi.abs().mean().detach() + self.actor_bc_weight * bc_loss

    def in_warm_start(self) -> bool:
        """Whether the next gradient step is one of the first ``bc_steps``, counted in ``_n_updates`` (saved with the
        model), not ``num_timesteps``, which RL-Zoo3 restarts at 0 when it continues a model."""
        return self._n_updates < self.bc_steps

    def _alpha_prime_learning_rate(self) -> float:
        """``cql_alpha_learning_rate``, or where it is ``None`` the critics' schedule at the current progress."""
        if self.cql_alpha_learning_rate is not None:
            return self.cql_alpha_learning_rate
        return self.lr_schedule(self._current_progress_remaining)

    def _actor_learning_rate(self) -> float:
        """The actor's schedule, or during the warm start the linear decay from ``bc_learning_rate`` to it."""
        learning_rate = self.actor_lr_schedule(self._current_progress_remaining)
        if self.bc_learning_rate is None or not self.in_warm_start():
            return learning_rate
        fraction = self._n_updates / self.bc_steps
        return self.bc_learning_rate + fraction * (learning_rate - self.bc_learning_rate)

    def sample_policy_actions(self, mean_actions: th.Tensor, log_std: th.Tensor, n: int) -> tuple[th.Tensor, th.Tensor]:
        """``n`` actions per state (state-major) of the distribution ``(mean_actions, log_std)``, and their
        log-densities: the actor's on ``n`` copies of each state, with only the sampling repeated."""
        mean_actions, log_std = mean_actions.repeat_interleave(n, dim=0), log_std.repeat_interleave(n, dim=0)
        return self.actor.action_dist.log_prob_from_params(mean_actions, log_std)

    def set_parameters(
        self, load_path_or_dict: str | dict[str, dict], exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """SB3's, across a change of the conservative weight's form given to ``load``: a saved multiplier's optimizer
        is left out where ``cql_target_action_gap=None`` fixes the weight, and where a target is given to a model
        saved with a fixed weight the multiplier starts at ``alpha'`` = 1."""
        params = load_path_or_dict
        if not isinstance(params, dict):
            _, params, _ = load_from_zip_file(params, device=device)
        params = dict(params)
        if self.alpha_prime_optimizer is None:
            params.pop("alpha_prime_optimizer", None)
        else:
            params.setdefault("alpha_prime_optimizer", self.alpha_prime_optimizer.state_dict())
        super().set_parameters(params, exact_match, device)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        if self.alpha_prime_optimizer is not None:
            state_dicts.append("alpha_prime_optimizer")
            variables.append("log_alpha_prime")
        return state_dicts, variables


def rare_reward_share(rewards: np.ndarray, rare: float = 0.05) -> float | None:
    """The share of transitions whose reward lies in the upper half of the rewards' range, where that share is under
    ``rare`` (a sparse reward: rare successes against a floor of small or constant rewards, whatever its scale and
    shift); ``None`` for a dense reward or a constant one."""
    rewards = np.asarray(rewards, dtype=np.float64).ravel()
    if rewards.size == 0 or not np.isfinite(rewards).all():
        return None
    low, high = rewards.min(), rewards.max()
    if high - low <= 1e-8 * max(1.0, abs(high)):
        return None
    share = float(np.mean(rewards > (low + high) / 2))
    return share if share < rare else None


def _append(logs: dict[str, list[float]], key: str, value: float) -> None:
    logs.setdefault(key, []).append(value)
