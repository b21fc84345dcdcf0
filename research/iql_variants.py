"""IQL variants kept for the studies in ``research/findings.md``, each a hook override of :class:`sb3_cql.IQL`.

- :class:`SuccessScaleIQL`: the critics and the value on the success scale, trained by binary cross-entropy
  (SHARSA's values; *The data's noisy actions hide the wrist's turn from every critic* and the runs named ``-bce``).
- :class:`DDPGBCIQL`: the actor by DDPG+BC, the anchor to the data unweighted (TD3+BC's extraction; the runs named
  ``iql-yaw-ddpgbc``).
- :class:`CappedIQL`: IQL with ``target_ceiling`` 1.0, the TD targets held at most the greatest return (fine-tuning
  past the climb of the critics' values, ``research/studies/finetune-iql``; through the zoo as ``iql_capped``,
  ``research/zoo_train.py``).
- :class:`OfflineAnchorIQL`: :class:`CappedIQL` whose actor's anchor reads only the offline half of a fine-tuning
  batch (whether the actor's drift online comes from imitating its own exploration; ``iql_offline_anchor``).

None is part of the package (nothing in ``sb3_cql`` imports this file); the first two were not better than the
shipped settings on the random-yaw data. Use them from Python, from the repository's root::

    from research.iql_variants import SuccessScaleIQL

    model = SuccessScaleIQL("MlpPolicy", env, dataset=..., expectile=0.5, n_steps=25, temperature=350.0)

A model saved by an earlier IQL with ``value_loss_type="bce"`` loads with ``SuccessScaleIQL.load(path)``; one saved with
``actor_loss_type="ddpg_bc"`` with ``DDPGBCIQL.load(path, actor_loss_type="awr")`` (the keyword this class ignores).
"""

from __future__ import annotations

from typing import Any

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from torch.nn import functional as F

from sb3_cql import IQL
from sb3_cql.common import MixedReplayBuffer, ReturnToGoReplayBuffer, SettingError


def expectile_bce_loss(logits: th.Tensor, targets: th.Tensor, expectile: float) -> th.Tensor:
    """The expectile loss on the success scale: the binary cross-entropy of the value's ``logits`` against the
    ``targets`` in [0, 1], each weighted ``|expectile - 1(u < 0)|`` with ``u = target - sigmoid(logit)``. At
    ``expectile`` 0.5 its minimum is the mean of the targets (SHARSA's value loss, halved, as IQL's expectile loss
    halves the squared error); above 0.5 it leans to the higher targets."""
    weight = th.where(targets < th.sigmoid(logits), 1.0 - expectile, expectile)
    return (weight * F.binary_cross_entropy_with_logits(logits, targets, reduction="none")).mean()


class SuccessScaleIQL(IQL):
    """IQL with its values on the success scale, as SHARSA's (Park et al. 2025): each network gives a logit, its value
    is the sigmoid of it, the TD targets ``r + (1 - d) * discount * sigmoid(V(s'))`` (kept in [0, 1]) and the twins'
    values are fitted by binary cross-entropy, the value by :func:`expectile_bce_loss`. No value can sink below a
    failure's 0 or rise above a success's 1. It needs rewards that are discounted success probabilities:
    ``reward_scale * r + reward_bias`` in [0, 1] at every step of the data. Its keywords are :class:`~sb3_cql.IQL`'s.
    """

    def _fill_from_dataset(self, dataset: Any) -> None:
        """IQL's, then a check that the critics' rewards are in [0, 1]."""
        super()._fill_from_dataset(dataset)
        rewards = self.reward_scale * self.replay_buffer.rewards[: self.replay_buffer.size()] + self.reward_bias
        if rewards.size and (rewards.min() < 0 or rewards.max() > 1):
            raise SettingError(
                "values on the success scale need the critics' rewards (reward_scale * reward + reward_bias) in [0, 1], "
                f"the data give {rewards.min():g} to {rewards.max():g}: set reward_scale and reward_bias so that a "
                "success is 1 and every other step 0"
            )

    def as_values(self, outputs: th.Tensor) -> th.Tensor:
        """The critics' or the value network's ``outputs`` (logits) as values, their sigmoid."""
        return th.sigmoid(outputs)

    def target_q_values(self, observations: th.Tensor, actions: th.Tensor) -> th.Tensor:
        q_values = self.as_values(th.cat(self.critic_target(observations, actions), dim=1))
        if self.q_agg == "mean":
            return q_values.mean(dim=1, keepdim=True)
        return q_values.min(dim=1, keepdim=True).values

    def state_values(self, observations: th.Tensor) -> th.Tensor:
        return self.as_values(self.value_net(observations))

    def value_loss(self, replay_data: ReplayBufferSamples, q_data: th.Tensor) -> th.Tensor:
        return expectile_bce_loss(self.value_net(replay_data.observations), q_data, self.expectile)

    def compute_target(self, replay_data: ReplayBufferSamples, discounts: th.Tensor | float) -> th.Tensor:
        # A reward of 1 that does not end the episode, met online, would take the target above 1.
        return super().compute_target(replay_data, discounts).clamp(0.0, 1.0)

    def critic_loss(self, replay_data: ReplayBufferSamples, target_q_values: th.Tensor) -> th.Tensor:
        logits = self.critic(replay_data.observations, replay_data.actions)
        return sum(F.binary_cross_entropy_with_logits(logit, target_q_values) for logit in logits)

    def ddpg_actor_loss(
        self, replay_data: ReplayBufferSamples, imitation_weights: th.Tensor, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """IQL's, with the critics' values at the actor's action on the success scale."""
        mean_actions, log_std, _ = self.actor.get_action_dist_params(replay_data.observations)
        actions_pi = th.tanh(mean_actions)
        q_pi = self.as_values(th.cat(self.critic(replay_data.observations, actions_pi), dim=1)).min(dim=1).values
        squared_errors = (actions_pi - replay_data.actions).pow(2).mean(dim=-1)
        logs.setdefault("train/actor_bc_loss", []).append(squared_errors.mean().item())
        spread = th.distributions.Normal(actions_pi.detach(), log_std.exp())
        spread_loss = -spread.log_prob(replay_data.actions).sum(dim=-1).mean()
        q_loss = -q_pi.mean() / q_pi.abs().mean().detach().clamp(min=1e-6)
        return q_loss + self.actor_bc_weight * (imitation_weights * squared_errors).mean() + spread_loss


class DDPGBCIQL(IQL):
    """IQL whose actor follows the critics' gradient anchored to the data's actions with every sample weighted
    equally (DDPG+BC, the extraction Park et al. 2024, https://arxiv.org/abs/2406.09329, found ahead of AWR on most
    of their tasks; TD3+BC's ``alpha`` is ``1 / actor_bc_weight``): :meth:`~sb3_cql.IQL.ddpg_actor_loss` with weights
    of 1. ``actor_loss_type`` is unused; the other keywords are :class:`~sb3_cql.IQL`'s."""

    def actor_loss(self, replay_data: ReplayBufferSamples, weights: th.Tensor, logs: dict[str, list[float]]) -> th.Tensor:
        return self.ddpg_actor_loss(replay_data, th.ones_like(weights), logs)


class CappedIQL(IQL):
    """:class:`~sb3_cql.IQL` with ``target_ceiling`` 1.0 unless given: every TD target at most the greatest return of a
    reward of 1 that ends the episode and 0 elsewhere. The studies' name for it (``iql_capped`` in the zoo), under which
    their models were saved; the keyword itself is IQL's.
    """

    def __init__(self, *args: Any, target_ceiling: float | None = 1.0, **kwargs: Any) -> None:
        super().__init__(*args, target_ceiling=target_ceiling, **kwargs)


class OfflineAnchorIQL(CappedIQL):
    """:class:`CappedIQL` fine-tuned with the ``ddpg_awr`` actor's anchor on the offline rows of each batch only: the
    online rows (the policy's own exploring actions) train the value and the critics, and enter the actor's loss
    through the critics' value at its actions, but the actor does not regress onto them. Each offline row's
    imitation weight is its advantage weight over their mean on the offline rows, so the anchor per offline row is
    as strong as in a batch of offline data only. Offline (no online transitions yet) it is :class:`CappedIQL`.
    Loads an :class:`~sb3_cql.IQL` model (``OfflineAnchorIQL.load(path, target_ceiling=1.0)``).
    """

    def actor_loss(self, replay_data: ReplayBufferSamples, weights: th.Tensor, logs: dict[str, list[float]]) -> th.Tensor:
        buffer = self.replay_buffer
        if self.actor_loss_type != "ddpg_awr" or not (isinstance(buffer, MixedReplayBuffer) and buffer.online.size()):
            return super().actor_loss(replay_data, weights, logs)
        n_offline = len(weights) - round(buffer.online_fraction * len(weights))  # MixedReplayBuffer: offline rows first
        return self.ddpg_actor_loss(replay_data, self.imitation_weights(replay_data, weights, n_offline, logs), logs)

    def imitation_weights(
        self, replay_data: ReplayBufferSamples, weights: th.Tensor, n_offline: int, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """The anchor's weight of each row of a batch whose first ``n_offline`` rows are offline data: theirs their
        advantage ``weights`` over their mean, scaled to the whole batch; the online rows' 0."""
        imitation = th.zeros_like(weights)
        if n_offline:
            imitation[:n_offline] = weights[:n_offline] / weights[:n_offline].mean() * (len(weights) / n_offline)
        return imitation


class SuccessAnchorIQL(OfflineAnchorIQL):
    """:class:`OfflineAnchorIQL` whose anchor also reads the online rows of the episodes that succeeded after them:
    an online row's imitation weight is 1 where its return-to-go is above 0 (the reward of 1 at a success came later
    in its episode) and 0 elsewhere, including the rows of an episode still running; the offline rows' is their
    advantage weight over its mean on them. The exploring episodes that succeed are imitated whatever the critics
    make of them. The buffers hold returns-to-go (:class:`~sb3_cql.common.ReturnToGoReplayBuffer`, as Cal-QL's), so
    the critics' rewards must be 0 but at a success: ``reward_bias`` 0. Logs ``train/online_success_rows``, the
    share of the online rows imitated. Loads an :class:`~sb3_cql.IQL` model
    (``SuccessAnchorIQL.load(path, target_ceiling=1.0)``).
    """

    def _check_settings(self) -> None:
        super()._check_settings()
        if self.reward_bias != 0:
            raise SettingError(
                f"SuccessAnchorIQL reads a success as a return-to-go above 0: reward_bias must be 0, got {self.reward_bias}"
            )

    def _fill_from_dataset(self, dataset: Any) -> None:
        """IQL's, then the buffer with its returns-to-go (its arrays shared)."""
        super()._fill_from_dataset(dataset)
        self.replay_buffer = ReturnToGoReplayBuffer.from_replay_buffer(
            self.replay_buffer, self.gamma, self.reward_scale, self.reward_bias
        )

    def imitation_weights(
        self, replay_data: ReplayBufferSamples, weights: th.Tensor, n_offline: int, logs: dict[str, list[float]]
    ) -> th.Tensor:
        imitation = (replay_data.returns_to_go.squeeze(1) > 0).to(weights.dtype)
        if n_offline:
            imitation[:n_offline] = weights[:n_offline] / weights[:n_offline].mean()
        logs.setdefault("train/online_success_rows", []).append(imitation[n_offline:].mean().item())
        return imitation
