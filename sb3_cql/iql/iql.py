"""Implicit Q-Learning (IQL) for offline RL: a critic trained in sample, an actor by advantage-weighted regression."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, ReplayBufferSamples
from stable_baselines3.common.utils import polyak_update, update_learning_rate
from torch.nn import functional as F

from sb3_cql.common.offline import OfflineSAC, frozen
from sb3_cql.common.settings import KeywordError, SettingError, check_finite, check_non_negative, finite_loss_value
from sb3_cql.iql.policies import CnnPolicy, IQLPolicy, MlpPolicy, MultiInputPolicy, ValueNetwork

if TYPE_CHECKING:
    from minari import MinariDataset

#: SAC's keywords of its entropy term, which IQL does not have.
ENTROPY_KEYWORDS = ("ent_coef", "target_entropy", "use_sde", "sde_sample_freq", "use_sde_at_warmup")
#: The actor's extractions from the critics (``actor_loss_type``).
ACTOR_LOSS_TYPES = ("awr", "ddpg_awr")
#: The combinations of the target twins (``q_agg``).
Q_AGGREGATIONS = ("min", "mean")


def expectile_loss(differences: th.Tensor, expectile: float) -> th.Tensor:
    """IQL's value loss, ``mean(|expectile - 1(u < 0)| * u^2)`` over the ``differences`` ``u = Q(s, a) - V(s)``."""
    weight = th.where(differences < 0, 1.0 - expectile, expectile)
    return (weight * differences.pow(2)).mean()


class IQL(OfflineSAC):
    """Implicit Q-Learning (Kostrikov, Nair and Levine 2021, https://arxiv.org/abs/2110.06169), trained offline.

    Every loss reads only the data's actions. Each gradient step (:meth:`train`, one hook a loss, in the reference
    code's order) fits the value by expectile regression on the target critics (:meth:`value_loss`), the actor by
    advantage-weighted regression (:meth:`actor_loss`; :meth:`ddpg_actor_loss` with ``actor_loss_type="ddpg_awr"``),
    the twin critics by TD to the next state's value (:meth:`compute_target`, :meth:`critic_loss`), then the targets
    by Polyak averaging. Everything else is :class:`~sb3_cql.common.OfflineSAC`'s. The defaults are
    ikostrikov/implicit_q_learning's MuJoCo settings and d3rlpy's ``IQLConfig``; ``hyperparams/iql.yml`` and
    ``hyperparams/iql_yaw.yml`` hold the Panda tasks'.

    :param policy: ``"MlpPolicy"``, ``"CnnPolicy"`` or ``"MultiInputPolicy"`` (SAC's, with IQL's actor and value
        network, :mod:`sb3_cql.iql.policies`).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id (a missing standard one is collected first), or a filled
        ``ReplayBuffer``; ``None`` for an empty buffer of ``buffer_size``.
    :param expectile: the value's expectile of Q over the data's actions, in [0.5, 1): 0.5 is SARSA's mean, higher is
        closer to the best action the data show.
    :param temperature: inverse temperature of the advantage weights (0: plain behaviour cloning).
    :param max_weight: the largest advantage weight.
    :param actor_loss_type: ``"awr"`` (the paper's) or ``"ddpg_awr"`` (the critics' gradient at the actor's action,
        anchored to the data's actions by the advantage weights).
    :param actor_bc_weight: with ``"ddpg_awr"``, the anchor's weight against the critics' normalised value, as CQL's.
    :param q_agg: how the target twins combine into the value's target and the advantages: ``"min"`` (the
        references') or ``"mean"``.
    :param target_floor: the least TD target, in the critics' units; ``None`` (the references'): no floor.
    :param target_ceiling: the greatest TD target, in the critics' units: the greatest return the rewards allow (1 for
        a reward of 1 that ends the episode and 0 elsewhere), so that the critics' own over-estimates, fed back through
        the value, cannot lift the values past it; ``None`` (the references'): no ceiling.
    :param actor_average_tau: act with an exponential moving average of the actor, moved towards it by this Polyak
        coefficient after each of its steps (saved with the model); ``None`` (the references'): act with the actor.
    :param normalize_observations: z-score the observations with the dataset's statistics inside the policy;
        ``False`` (the references') reads them raw; ``None`` z-scores them for an ``MlpPolicy`` on Box observations.
    :param kwargs: the offline base's keywords (:class:`~sb3_cql.common.OfflineSAC`; ``learning_rate`` is the
        critics' and the value network's) and SAC's but its entropy's.
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
        expectile: float = 0.7,
        temperature: float = 3.0,
        max_weight: float = 100.0,
        actor_loss_type: str = "awr",
        actor_bc_weight: float = 0.4,
        q_agg: str = "min",
        target_floor: float | None = None,
        target_ceiling: float | None = None,
        actor_average_tau: float | None = None,
        normalize_observations: bool | None = False,
        **kwargs: Any,
    ) -> None:
        self.expectile = expectile
        self.temperature = temperature
        self.max_weight = max_weight
        self.actor_loss_type = actor_loss_type
        self.actor_bc_weight = actor_bc_weight
        self.q_agg = q_agg
        self.target_floor = target_floor
        self.target_ceiling = target_ceiling
        self.actor_average_tau = actor_average_tau
        entropy = sorted(set(kwargs) & set(ENTROPY_KEYWORDS))
        if entropy:
            raise KeywordError(f"IQL does not take {', '.join(entropy)}: its actor has no entropy term")
        # No entropy term: SAC's coefficient stays a constant 0, never learned.
        super().__init__(policy, env, dataset, normalize_observations=normalize_observations, ent_coef=0.0, **kwargs)

    @classmethod
    def known_keywords(cls) -> set[str]:
        """The offline base's keywords and SAC's, but its entropy term's."""
        return super().known_keywords() - set(ENTROPY_KEYWORDS)

    def _check_settings(self) -> None:
        """OfflineSAC's checks, and those of IQL's own settings."""
        super()._check_settings()
        expectile = self.expectile
        if not (isinstance(expectile, (int, float)) and not isinstance(expectile, bool) and 0.5 <= expectile < 1):
            raise SettingError(f"expectile must be in [0.5, 1), got {expectile!r}")
        check_non_negative([("temperature", self.temperature)])
        check_non_negative([("max_weight", self.max_weight)], strictly=True)
        check_non_negative([("actor_bc_weight", self.actor_bc_weight)])
        floor, ceiling = self.target_floor, self.target_ceiling
        bounds = (("target_floor", floor), ("target_ceiling", ceiling))
        check_finite([(name, value) for name, value in bounds if value is not None])
        if floor is not None and ceiling is not None and ceiling < floor:
            raise SettingError(f"target_ceiling {ceiling!r} is below target_floor {floor!r}: the TD targets lie between them")
        tau = self.actor_average_tau
        if tau is not None and not (isinstance(tau, (int, float)) and not isinstance(tau, bool) and 0 < tau <= 1):
            raise SettingError(f"actor_average_tau must be a number in (0, 1] or None, got {tau!r}")
        for name, choices in (("q_agg", Q_AGGREGATIONS), ("actor_loss_type", ACTOR_LOSS_TYPES)):
            if getattr(self, name) not in choices:
                raise SettingError(f"{name} must be one of {', '.join(map(repr, choices))}, got {getattr(self, name)!r}")
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

    def train(self, gradient_steps: int, batch_size: int = 256) -> None:
        """IQL's update (the class docstring), ``gradient_steps`` times. Logs ``train/actor_loss``,
        ``train/critic_loss``, ``train/value_loss`` and ``train/iql_*`` (``iql_weight``: the mean advantage weight)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.critic.optimizer, self.value_net.optimizer])
        update_learning_rate(self.actor.optimizer, self.actor_lr_schedule(self._current_progress_remaining))
        logs: dict[str, list[float]] = {}

        for _ in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma

            # The value: an expectile of the target critics' values of the data's actions.
            with th.no_grad():
                q_data = self.target_q_values(replay_data.observations, replay_data.actions)
            value_loss = self.value_loss(replay_data, q_data)
            self._step(self.value_net.optimizer, value_loss, "IQL's value loss")

            # The actor: the data's actions weighted by their advantages under the value just updated.
            with th.no_grad():
                value = self.state_values(replay_data.observations)
                advantage = q_data - value
            weights = th.exp(self.temperature * advantage).clamp(max=self.max_weight).squeeze(1)
            actor_loss = self.actor_loss(replay_data, weights, logs)
            self._step(self.actor.optimizer, actor_loss, "IQL's actor loss")
            self.update_actor_average()

            # The critics: TD to the value of the next state.
            with th.no_grad():
                target_q_values = self.compute_target(replay_data, discounts)
            critic_loss = self.critic_loss(replay_data, target_q_values)
            critic_loss_value = self._step(self.critic.optimizer, critic_loss, "IQL's critic loss")

            # The target critics.
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

    # The value.

    def target_q_values(self, observations: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """``Q'(s, a)``, ``(batch, 1)``: the target twins' values combined by ``q_agg``."""
        q_values = th.cat(self.critic_target(observations, actions), dim=1)
        if self.q_agg == "mean":
            return q_values.mean(dim=1, keepdim=True)
        return q_values.min(dim=1, keepdim=True).values

    def state_values(self, observations: th.Tensor) -> th.Tensor:
        """``V(s)`` as the advantages and the TD target read it, ``(batch, 1)``."""
        return self.value_net(observations)

    def value_loss(self, replay_data: ReplayBufferSamples, q_data: th.Tensor) -> th.Tensor:
        """The expectile regression of ``V(s)`` on ``q_data``, the batch's ``Q'(s, a)`` (:func:`expectile_loss`)."""
        return expectile_loss(q_data - self.value_net(replay_data.observations), self.expectile)

    # The actor.

    def actor_loss(self, replay_data: ReplayBufferSamples, weights: th.Tensor, logs: dict[str, list[float]]) -> th.Tensor:
        """``-mean(w * log pi(a | s))`` for the advantage weights ``w``, ``(batch,)``; with ``"ddpg_awr"``,
        :meth:`ddpg_actor_loss` with the anchor weighted by ``w / mean(w)``."""
        if self.actor_loss_type == "ddpg_awr":
            return self.ddpg_actor_loss(replay_data, weights / weights.mean(), logs)
        return -(weights * self.actor.log_prob_of(replay_data.observations, replay_data.actions)).mean()

    def ddpg_actor_loss(
        self, replay_data: ReplayBufferSamples, imitation_weights: th.Tensor, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """TD3+BC's actor loss with each sample's imitation weighted: ``-mean(Q) / mean(|Q|) + actor_bc_weight *
        mean(imitation_weights * |tanh(mu(s)) - a|^2 / action_dim)`` (the denominator detached), plus the likelihood
        of the data's actions under the spread around the detached mean. Logs ``train/actor_bc_loss``, unweighted."""
        mean_actions, log_std, _ = self.actor.get_action_dist_params(replay_data.observations)
        actions_pi = th.tanh(mean_actions)
        with frozen(self.critic) as critic:
            q_pi = th.cat(critic(replay_data.observations, actions_pi), dim=1).min(dim=1).values
        squared_errors = (actions_pi - replay_data.actions).pow(2).mean(dim=-1)
        logs.setdefault("train/actor_bc_loss", []).append(squared_errors.mean().item())
        spread = th.distributions.Normal(actions_pi.detach(), log_std.exp())
        spread_loss = -spread.log_prob(replay_data.actions).sum(dim=-1).mean()
        q_loss = -q_pi.mean() / q_pi.abs().mean().detach().clamp(min=1e-6)
        return q_loss + self.actor_bc_weight * (imitation_weights * squared_errors).mean() + spread_loss

    def update_actor_average(self) -> None:
        """With ``actor_average_tau``, Polyak-move the average the model acts with towards the actor."""
        if self.actor_average_tau is not None:  # the policy then keeps an average (_setup_model)
            polyak_update(self.actor.parameters(), self.policy.actor_average.parameters(), self.actor_average_tau)

    # The critics.

    def compute_target(self, replay_data: ReplayBufferSamples, discounts: th.Tensor | float) -> th.Tensor:
        """``rewards + (1 - dones) * discounts * V(s')`` (:meth:`critic_rewards`), raised to ``target_floor`` and
        lowered to ``target_ceiling``."""
        next_values = self.state_values(replay_data.next_observations)
        target = self.critic_rewards(replay_data) + (1 - replay_data.dones) * discounts * next_values
        if self.target_floor is None and self.target_ceiling is None:
            return target
        return target.clamp(min=self.target_floor, max=self.target_ceiling)

    def critic_loss(self, replay_data: ReplayBufferSamples, target_q_values: th.Tensor) -> th.Tensor:
        """Each critic's mean squared error to the TD target at the data's actions, summed (not SAC's halved)."""
        current_q_values = self.critic(replay_data.observations, replay_data.actions)
        return sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)

    def _step(self, optimizer: th.optim.Optimizer, loss: th.Tensor, description: str) -> float:
        """One optimizer step on ``loss`` unless it is not finite (:class:`~sb3_cql.common.TrainingDivergedError`)."""
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
