"""Conservative Q-Learning (CQL(H)) for offline RL: SAC plus a conservative term in the critic loss."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch as th
from minari import MinariDataset
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import polyak_update, update_learning_rate
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN
from torch.nn import functional as F

from sb3_cql.common import OfflineSAC, ReturnToGoReplayBuffer, behaviour_cloning_loss
from sb3_cql.cql.fused_mlp import relu_mlp, relu_mlp_parameters

#: Bound of the learned Lagrange multiplier, as in the reference implementation.
MAX_ALPHA_PRIME = 1e6


class TrainingDivergedError(FloatingPointError, ValueError):
    """The critic loss became NaN or infinite. A ``ValueError`` too, so that RL-Zoo3's tuning prunes the trial
    (it prunes on ``ValueError``) instead of ending the whole study."""


class CQL(OfflineSAC):
    """Conservative Q-Learning, CQL(H) (Kumar et al. 2020, https://arxiv.org/abs/2006.04779), trained offline.

    :meth:`train` is SAC's with one more critic loss term: for each critic,

    ``cql_alpha * (T * logsumexp_a(Q(s, a) / T) - Q(s, a_data))``

    where the log-sum-exp runs over ``cql_n_actions`` uniform actions, ``cql_n_actions`` current-policy actions at
    ``s`` and ``cql_n_actions`` policy actions at ``s'`` (all scored at ``s``), importance-weighted by their
    densities, and ``T`` is ``cql_temperature``. With ``cql_target_action_gap`` set, the term becomes
    ``alpha' * (term - gap)`` with the multiplier ``alpha'`` learned by dual gradient ascent.

    Training is offline (:class:`~sb3_cql.common.OfflineSAC`): the replay buffer is filled from ``dataset`` and
    :meth:`learn` makes one gradient step per timestep, stepping the env never (it only gives the spaces, and
    callbacks such as ``EvalCallback`` use their own envs). Observations are z-scored with the dataset's
    statistics (``normalize_observations``) inside the policy, so ``predict`` applies the same normalisation after
    ``save``/``load``. With ``online_fraction``, :meth:`learn` fine-tunes online, the dataset kept in the buffer
    (the same loss; ``cql_calibrated`` gives new episodes their returns-to-go when they end).

    Defaults follow the thesis's Table A.1 where it gives a value (batch 352, critic learning rate 3e-4, actor
    learning rate 3e-5, tau 5e-3, 10 sampled actions) and the reference implementations elsewhere.

    :param policy: the policy model (``"MlpPolicy"``, ``"MultiInputPolicy"``: SAC's).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id, or a filled ``ReplayBuffer``; ``None`` for an empty buffer of
        ``buffer_size`` (filled by hand, e.g. with :func:`sb3_cql.data.fill_replay_buffer`). A missing standard
        id (``sb3cql/Panda-v0/pid-v0``, ...) is collected first (:func:`sb3_cql.data.ensure_dataset`).
    :param learning_rate: learning rate of the critics, the entropy coefficient and the Lagrange multiplier.
    :param actor_learning_rate: learning rate of the actor; ``None`` for ``learning_rate``.
    :param buffer_size: size of an empty replay buffer when ``dataset`` is ``None``.
    :param batch_size: minibatch size of each gradient step.
    :param tau: Polyak coefficient of the target critics.
    :param gamma: discount factor.
    :param ent_coef: SAC's entropy coefficient (``"auto"`` to learn it).
    :param target_entropy: SAC's target entropy when learning ``ent_coef``.
    :param target_update_interval: gradient steps between target updates.
    :param cql_alpha: weight of the conservative term.
    :param cql_n_actions: actions sampled per state for each of the three log-sum-exp groups.
    :param cql_temperature: temperature ``T`` of the log-sum-exp.
    :param cql_target_action_gap: with a value, learn a Lagrange multiplier that keeps the conservative gap near it.
    :param cql_deterministic_backup: drop the entropy term from the TD target (as d3rlpy and the CQL paper's code).
    :param cql_max_backup: back up the max over ``cql_n_actions`` next-state policy actions instead of one sample.
    :param cql_calibrated: calibrated CQL, Cal-QL (Nakamoto et al. 2023, https://arxiv.org/abs/2303.05479): in the
        conservative term, Q at the policy's actions (at ``s`` and ``s'``) is replaced by ``max(Q, G(s))``, with
        ``G(s)`` the discounted return-to-go of the data's episode from ``s`` under the critics' rewards
        (``reward_scale``, ``reward_bias``), so the term stops pushing the policy's values below what the data earned.
        The replay buffer becomes a :class:`~sb3_cql.common.ReturnToGoReplayBuffer` (returns-to-go computed when the
        data are loaded, and for online episodes when they end). ``train/cql_bound_rate`` logs the fraction of
        policy-action values the bound lifted.
    :param bc_steps: gradient steps at the start of training (counted across ``learn`` calls and ``save``/``load``)
        whose actor loss is behaviour cloning in place of the Q-value (the deterministic action fitted to the data
        actions by least squares), next to the entropy term, which sets the spread alone (through the log-std head);
        the critics train as usual meanwhile.
    :param bc_learning_rate: the actor's learning rate at the start of the warm start, decaying linearly over
        ``bc_steps`` to ``actor_learning_rate`` (imitation needs a larger rate than following Q, and a clone settles
        only as its rate decays); ``None`` for ``actor_learning_rate`` throughout.
    :param actor_bc_weight: after the warm start, keep imitating in the actor loss: SAC's actor loss divided by the
        batch's mean ``|Q|`` (detached) plus ``actor_bc_weight`` times the warm start's behaviour-cloning loss, as in
        TD3+BC (Fujimoto & Gu 2021, https://arxiv.org/abs/2106.06860), whose ``alpha`` is ``1 / actor_bc_weight``
        (its default 2.5 is 0.4 here). ``0`` (the default) is CQL's actor loss as defined. Measured on a training seed
        (the documentation's *What we learned* page): without it, following Q broke a working clone within 1,000
        steps; with a weight of 4 the clone held through 21,000 Q steps, neither better nor worse than the clone on
        the three tasks; with 1 it slipped.
    :param reward_scale: the critics learn from ``reward_scale * reward + reward_bias`` (the buffer keeps the data's
        rewards). With a sparse 0/1 reward, a negative bias (the thesis's code: scale 4, bias -2) gives every step
        that does not reach the goal a cost, and puts the Q-values on the scale of ``cql_target_action_gap``.
    :param reward_bias: see ``reward_scale``.
    :param normalize_observations: z-score Box observations with the dataset's mean and std.
    :param online_fraction: ``None`` (the default) trains offline. A fraction fine-tunes online: :meth:`learn` steps
        the env as SAC's does, timesteps are env steps, the offline data stay in the replay buffer (a
        :class:`~sb3_cql.common.MixedReplayBuffer`) and every batch draws this fraction of its samples from the online
        transitions (RLPD's symmetric sampling: 0.5). Given to :meth:`load`, it fine-tunes a model trained offline.
    :param online_buffer_size: capacity of the online transitions when fine-tuning.
    :param learning_starts: env steps of uniform random actions before training starts, when fine-tuning (SAC's;
        0 keeps the trained policy acting from the first step).
    :param train_freq: env steps (or ``(n, "episode")``) between two trainings, when fine-tuning (SAC's).
    :param gradient_steps: gradient steps of each training, when fine-tuning (SAC's; ``-1``: as many as env steps).
    :param action_noise: noise added to the actions when fine-tuning (SB3's ``ActionNoise``, as SAC's and TD3's).
    :param deterministic_rollouts: when fine-tuning, act with the deterministic action plus ``action_noise`` (TD3's
        exploration) instead of a sample of the policy (SAC's).
    :param tensorboard_log: TensorBoard log folder.
    :param policy_kwargs: keywords of the policy (``net_arch``, ...).
    :param verbose: 0 silent, 1 training logs, 2 debug.
    :param seed: seed of the random generators.
    :param device: torch device.
    :param _init_setup_model: build the networks now.
    """

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str,
        dataset: MinariDataset | str | ReplayBuffer | None = None,
        learning_rate: float | Schedule = 3e-4,
        actor_learning_rate: float | Schedule | None = 3e-5,
        buffer_size: int = 2_000_000,
        batch_size: int = 352,
        tau: float = 0.005,
        gamma: float = 0.99,
        ent_coef: str | float = "auto",
        target_entropy: str | float = "auto",
        target_update_interval: int = 1,
        cql_alpha: float = 5.0,
        cql_n_actions: int = 10,
        cql_temperature: float = 1.0,
        cql_target_action_gap: float | None = None,
        cql_deterministic_backup: bool = True,
        cql_max_backup: bool = False,
        cql_calibrated: bool = False,
        bc_steps: int = 0,
        bc_learning_rate: float | None = None,
        actor_bc_weight: float = 0.0,
        reward_scale: float = 1.0,
        reward_bias: float = 0.0,
        normalize_observations: bool = True,
        online_fraction: float | None = None,
        online_buffer_size: int = 1_000_000,
        learning_starts: int = 0,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        deterministic_rollouts: bool = False,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if cql_n_actions < 1 or cql_temperature <= 0 or cql_alpha < 0 or not actor_bc_weight >= 0:
            raise ValueError("cql_n_actions must be >= 1, cql_temperature > 0, cql_alpha >= 0 and actor_bc_weight >= 0")
        self.cql_alpha = cql_alpha
        self.cql_n_actions = cql_n_actions
        self.cql_temperature = cql_temperature
        self.cql_target_action_gap = cql_target_action_gap
        self.cql_deterministic_backup = cql_deterministic_backup
        self.cql_max_backup = cql_max_backup
        self.cql_calibrated = cql_calibrated
        self.bc_steps = bc_steps
        self.bc_learning_rate = bc_learning_rate
        self.actor_bc_weight = actor_bc_weight
        self.reward_scale = reward_scale
        self.reward_bias = reward_bias
        self.log_alpha_prime: th.Tensor | None = None
        self.alpha_prime_optimizer: th.optim.Adam | None = None
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
            policy_kwargs=policy_kwargs,
            batch_size=batch_size,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            tau=tau,
            gamma=gamma,
            ent_coef=ent_coef,
            target_entropy=target_entropy,
            target_update_interval=target_update_interval,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=_init_setup_model,
        )

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.cql_calibrated and not isinstance(self.replay_buffer, ReturnToGoReplayBuffer):
            self._calibrate_buffer()
        if self.cql_target_action_gap is not None:
            self.log_alpha_prime = th.zeros(1, device=self.device, requires_grad=True)
            self.alpha_prime_optimizer = th.optim.Adam([self.log_alpha_prime], lr=self.lr_schedule(1))

    def _fill_from_dataset(self, dataset: MinariDataset | str | ReplayBuffer) -> None:
        super()._fill_from_dataset(dataset)
        if self.cql_calibrated:
            self._calibrate_buffer()

    def _calibrate_buffer(self) -> None:
        """The replay buffer as a :class:`ReturnToGoReplayBuffer` (its arrays shared) under this model's rewards."""
        assert self.replay_buffer is not None
        self.replay_buffer = ReturnToGoReplayBuffer.from_replay_buffer(
            self.replay_buffer, self.gamma, self.reward_scale, self.reward_bias
        )

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SAC's update with the conservative term added to the critic loss (and, with ``cql_target_action_gap``,
        a dual step on the Lagrange multiplier)."""
        self.policy.set_training_mode(True)
        optimizers = [self.critic.optimizer]
        optimizers += [opt for opt in (self.ent_coef_optimizer, self.alpha_prime_optimizer) if opt is not None]
        self._update_learning_rate(optimizers)
        actor_learning_rate = self._actor_learning_rate()
        update_learning_rate(self.actor.optimizer, actor_learning_rate)
        self.logger.record("train/actor_learning_rate", actor_learning_rate)
        logs: dict[str, list[float]] = {}

        for _ in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            # The actor runs once on s and once on s' per step; every sample below is drawn from these parameters
            # (the actor changes only at the end of the step).
            policy = self.actor.get_action_dist_params(data.observations)[:2]
            actions_pi, log_prob = self.actor.action_dist.log_prob_from_params(*policy)
            log_prob = log_prob.reshape(-1, 1)
            with th.no_grad():
                next_policy = self.actor.get_action_dist_params(data.next_observations)[:2]

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
                rewards = self.reward_scale * data.rewards + self.reward_bias
                next_q_values = self._next_q_values(data.next_observations, next_policy, ent_coef)
                target_q_values = rewards + (1 - data.dones) * self.gamma * next_q_values

            detached_policy = (policy[0].detach(), policy[1].detach())
            current_q_values, conservative, diagnostics = self._q_values_and_conservative_terms(
                data, detached_policy, next_policy
            )
            td_loss = 0.5 * sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
            conservative_loss = self._conservative_loss(conservative, logs)
            critic_loss = td_loss + conservative_loss
            critic_loss_value = critic_loss.item()
            if not math.isfinite(critic_loss_value):
                raise TrainingDivergedError(
                    f"CQL's critic loss is {critic_loss_value} at gradient step {self.num_timesteps + 1}: training "
                    f"diverged (try a lower learning_rate, reward scaling or cql_target_action_gap)"
                )
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()

            if self._in_warm_start():
                # Behaviour-cloning warm start: in SAC's actor loss, imitation in place of Q. The deterministic action
                # is fitted by least squares (as sb3_cql.BC: the mean of a tanh-Gaussian fitted by likelihood is biased
                # when data actions saturate at +-1, as the gripper's do); the spread is SAC's, set by the entropy
                # term against the target entropy, and trains the log-std head only: through the shared layers it
                # moved the mean enough to break a working grasp within a few hundred steps. (A likelihood of the data
                # actions for the spread made the policy's samples bang-bang on the noisy data, whose clipped actions
                # often sit at +-1; the conservative term then kept Q at the policy's samples tens below Q at the data
                # actions, and the backup carried that gap into every Q-value: docs/findings.md.)
                mean_actions, log_std = self._imitation_dist_params(data.observations)
                _, spread_log_prob = self.actor.action_dist.log_prob_from_params(mean_actions.detach(), log_std)
                actor_loss = (ent_coef * spread_log_prob).mean() + behaviour_cloning_loss(mean_actions, data.actions)
            else:
                q_values_pi = th.cat(self.critic(data.observations, actions_pi), dim=1)
                min_qf_pi, _ = th.min(q_values_pi, dim=1, keepdim=True)
                actor_loss = (ent_coef * log_prob - min_qf_pi).mean()
                if self.actor_bc_weight > 0:
                    # TD3+BC's anchor: the Q term on a scale of 1 whatever the rewards, plus imitation of the data.
                    bc_loss = behaviour_cloning_loss(policy[0], data.actions)
                    _append(logs, "train/actor_bc_loss", bc_loss.item())
                    actor_loss = actor_loss / min_qf_pi.abs().mean().detach() + self.actor_bc_weight * bc_loss
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
            for key, value in diagnostics.items():
                _append(logs, key, value)

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(key, float(np.mean(values)))

    def _in_warm_start(self) -> bool:
        """Whether the next gradient step is one of the first ``bc_steps`` of the model's training. Counted in gradient
        steps made (``_n_updates``, saved with the model), not ``num_timesteps``: RL-Zoo3 continues a saved model
        (``-i``) with the count of timesteps restarted at 0."""
        return self._n_updates < self.bc_steps

    def _actor_learning_rate(self) -> float:
        """The actor's schedule, or during the warm start the linear decay from ``bc_learning_rate`` to it."""
        learning_rate = self.actor_lr_schedule(self._current_progress_remaining)
        if self.bc_learning_rate is None or not self._in_warm_start():
            return learning_rate
        fraction = self._n_updates / self.bc_steps
        return self.bc_learning_rate + fraction * (learning_rate - self.bc_learning_rate)

    def _imitation_dist_params(self, observations: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The actor's mean actions and log-std (``Actor.get_action_dist_params``), with the log-std head fed the
        shared layers' output detached: gradients of the log-std reach that head only."""
        features = self.actor.extract_features(observations, self.actor.features_extractor)
        latent_pi = self.actor.latent_pi(features)
        log_std = th.clamp(self.actor.log_std(latent_pi.detach()), LOG_STD_MIN, LOG_STD_MAX)
        return self.actor.mu(latent_pi), log_std

    def _next_q_values(
        self, next_observations: th.Tensor, next_policy: tuple[th.Tensor, th.Tensor], ent_coef: th.Tensor
    ) -> th.Tensor:
        """The soft (or, with ``cql_deterministic_backup``, plain) value of the next states under the target critics,
        for a policy sample (or the best of ``cql_n_actions`` with ``cql_max_backup``) from ``next_policy``'s
        (mean actions, log-std)."""
        n_samples = self.cql_n_actions if self.cql_max_backup else 1
        next_actions, next_log_prob = self._sample_actions(*next_policy, n_samples)
        if n_samples > 1:
            next_observations = next_observations.repeat_interleave(n_samples, dim=0)
        next_q_values = th.cat(self.critic_target(next_observations, next_actions), dim=1)
        next_q_values, _ = th.min(next_q_values, dim=1, keepdim=True)
        if not self.cql_deterministic_backup:
            next_q_values = next_q_values - ent_coef * next_log_prob.reshape(-1, 1)
        if n_samples > 1:
            next_q_values = next_q_values.reshape(-1, n_samples).max(dim=1, keepdim=True).values
        return next_q_values

    def _q_values_and_conservative_terms(
        self, data, policy: tuple[th.Tensor, th.Tensor], next_policy: tuple[th.Tensor, th.Tensor]
    ) -> tuple[list[th.Tensor], list[th.Tensor], dict[str, float]]:
        """Q on the data actions and each critic's ``logsumexp - Q(data)`` gap, from one critic forward pass over the
        data actions and the ``3 * cql_n_actions`` sampled actions of every state (the policy's, drawn from its
        (mean actions, log-std) at s and at s')."""
        batch_size, n = data.observations.shape[0], self.cql_n_actions
        action_dim = self.action_space.shape[0]
        with th.no_grad():
            random_actions = th.empty(batch_size * n, action_dim, device=self.device).uniform_(-1.0, 1.0)
            policy_actions, policy_log_prob = self._sample_actions(*policy, n)
            next_policy_actions, next_policy_log_prob = self._sample_actions(*next_policy, n)
        observations = th.cat([data.observations, data.observations.repeat_interleave(n, dim=0).repeat(3, 1)])
        actions = th.cat([data.actions, random_actions, policy_actions, next_policy_actions])
        # Importance weights: uniform density (1/2)^|A| on [-1, 1]^|A|, the policy's own density otherwise.
        log_densities = th.cat(
            [
                th.full((batch_size, n), action_dim * math.log(0.5), device=self.device),
                policy_log_prob.reshape(batch_size, n),
                next_policy_log_prob.reshape(batch_size, n),
            ],
            dim=1,
        )
        current_q_values, gaps, diagnostics = [], [], {}
        for index, q_values in enumerate(self._critic_q_values(observations, actions), start=1):
            q_data = q_values[:batch_size]
            sampled = q_values[batch_size:].reshape(3, batch_size, n)
            raw_sampled = sampled
            if self.cql_calibrated:
                # Cal-QL: the policy's values are pushed down no further than the data's return-to-go.
                bound = data.returns_to_go
                sampled = th.cat([sampled[:1], th.maximum(sampled[1:], bound)])
            importance_weighted = th.cat(list(sampled), dim=1) - log_densities
            logsumexp = th.logsumexp(importance_weighted / self.cql_temperature, dim=1) * self.cql_temperature
            current_q_values.append(q_data)
            gaps.append(logsumexp.mean() - q_data.mean())
            if index == 1:
                diagnostics = {
                    "train/cql_q_data": q_data.mean().item(),
                    "train/cql_q_random": raw_sampled[0].mean().item(),
                    "train/cql_q_policy": raw_sampled[1].mean().item(),
                    "train/cql_q_next_policy": raw_sampled[2].mean().item(),
                    "train/cql_gap": gaps[0].item(),
                }
                if self.cql_calibrated:
                    diagnostics["train/cql_bound_rate"] = (raw_sampled[1:] < bound).float().mean().item()
        return current_q_values, gaps, diagnostics

    def _critic_q_values(self, observations: th.Tensor, actions: th.Tensor) -> list[th.Tensor]:
        """``self.critic(observations, actions)``, through :func:`relu_mlp` when the Q-networks are ReLU MLPs."""
        networks = [relu_mlp_parameters(q_net) for q_net in self.critic.q_networks]
        if any(parameters is None for parameters in networks):
            return list(self.critic(observations, actions))
        with th.set_grad_enabled(not self.critic.share_features_extractor):
            features = self.critic.extract_features(observations, self.critic.features_extractor)
        inputs = th.cat([features, actions], dim=1)
        return [relu_mlp(inputs, parameters) for parameters in networks]  # type: ignore[arg-type]

    def _sample_actions(self, mean_actions: th.Tensor, log_std: th.Tensor, n: int) -> tuple[th.Tensor, th.Tensor]:
        """``n`` actions per state (state-major order) of the policy whose ``get_action_dist_params`` gave
        ``mean_actions`` and ``log_std``, and their log-densities.

        Only the sampling is repeated: the same distribution as running the actor on ``n`` copies of each state, at
        a fraction of the cost. (CQL has no gSDE: SB3 sets the policy's ``use_sde`` from the algorithm's, False.)
        """
        mean_actions, log_std = mean_actions.repeat_interleave(n, dim=0), log_std.repeat_interleave(n, dim=0)
        return self.actor.action_dist.log_prob_from_params(mean_actions, log_std)

    def _conservative_loss(self, gaps: list[th.Tensor], logs: dict[str, list[float]]) -> th.Tensor:
        """``cql_alpha`` times the gaps, or their Lagrangian with a dual step on the multiplier."""
        terms = [self.cql_alpha * gap for gap in gaps]
        if self.log_alpha_prime is None or self.alpha_prime_optimizer is None:
            return sum(terms)
        alpha_prime = self.log_alpha_prime.exp().clamp(0.0, MAX_ALPHA_PRIME)
        # Dual ascent: the multiplier grows while the gap exceeds its target.
        alpha_prime_loss = -0.5 * sum(alpha_prime * (term.detach() - self.cql_target_action_gap) for term in terms)
        self.alpha_prime_optimizer.zero_grad()
        alpha_prime_loss.backward()
        self.alpha_prime_optimizer.step()
        _append(logs, "train/cql_alpha_prime", alpha_prime.item())
        _append(logs, "train/cql_alpha_prime_loss", alpha_prime_loss.item())
        return sum(alpha_prime.detach() * (term - self.cql_target_action_gap) for term in terms)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        if self.alpha_prime_optimizer is not None:
            state_dicts.append("alpha_prime_optimizer")
            variables.append("log_alpha_prime")
        return state_dicts, variables


def _append(logs: dict[str, list[float]], key: str, value: float) -> None:
    logs.setdefault(key, []).append(value)
