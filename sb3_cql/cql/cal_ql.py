"""Calibrated Conservative Q-Learning (Cal-QL): CQL whose conservative term stops at the data's return-to-go."""

from __future__ import annotations

from typing import ClassVar

import torch as th
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_cql.cql.cql import CQL


class CalQL(CQL):
    """Cal-QL (Nakamoto et al. 2023, https://arxiv.org/abs/2303.05479): :class:`~sb3_cql.CQL` whose conservative term
    sees the policy's values (at ``s`` and ``s'``) as ``max(Q, G(s))``, with ``G(s)`` the discounted return-to-go of
    the data's episode from ``s`` under the critics' rewards (``reward_scale``, ``reward_bias``), so the term stops
    pushing them below what the data earned. It overrides one hook, :meth:`policy_values_in_logsumexp`.

    The replay buffer is a :class:`~sb3_cql.common.ReturnToGoReplayBuffer` (returns-to-go computed when the data are
    loaded, and for online episodes when they end; ``-inf``, no bound, until then). ``train/cql_bound_rate`` logs the
    fraction of the first critic's policy-action values the bound lifted.

    Its keywords are :class:`~sb3_cql.CQL`'s, ``cql_calibrated`` always ``True``; ``CQL(..., cql_calibrated=True)``
    and ``CQL.load`` of a model saved with it make a ``CalQL``.
    """

    needs_returns_to_go: ClassVar[bool] = True

    def _setup_model(self) -> None:
        self.cql_calibrated = True  # saved with the model: CQL.load makes it a CalQL again
        super()._setup_model()

    def policy_values_in_logsumexp(
        self, q_policy: th.Tensor, replay_data: ReplayBufferSamples, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """``max(Q, G(s))``: the policy's values bounded below by the batch's returns-to-go."""
        returns_to_go = replay_data.returns_to_go  # type: ignore[attr-defined]
        logs.setdefault("train/cql_bound_rate", []).append((q_policy[0] < returns_to_go).float().mean().item())
        return th.maximum(q_policy, returns_to_go)
