"""Calibrated Conservative Q-Learning (Cal-QL): CQL whose conservative term stops at the data's return-to-go."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_cql.common.buffers import ReturnToGoReplayBuffer
from sb3_cql.common.settings import SettingError
from sb3_cql.cql.cql import CQL


class CalQL(CQL):
    """Cal-QL (Nakamoto et al. 2023, https://arxiv.org/abs/2303.05479): :class:`~sb3_cql.CQL` whose conservative term
    sees the policy's values as ``max(Q, G(s))``, ``G(s)`` the discounted return-to-go of the data's episode under the
    critics' rewards (:meth:`policy_values_in_logsumexp`), from a :class:`~sb3_cql.common.ReturnToGoReplayBuffer`.
    ``train/cql_bound_rate`` logs the fraction of the first critic's values the bound lifted. Its keywords are
    :class:`~sb3_cql.CQL`'s; in the zoo it is ``--algo calql``.
    """

    def _check_settings(self) -> None:
        super()._check_settings()
        if self.action_chunk > 1:
            raise SettingError("CalQL does not support action_chunk > 1 yet (returns-to-go of chunk samples)")

    def _setup_model(self) -> None:
        if isinstance(self.observation_space, spaces.Dict):
            raise SettingError("CalQL does not support Dict observations (returns-to-go need a Box buffer)")
        super()._setup_model()
        if not isinstance(self.replay_buffer, ReturnToGoReplayBuffer):  # a loaded model's one-transition buffer
            self._add_returns_to_go()

    def _fill_from_dataset(self, dataset: Any) -> None:
        super()._fill_from_dataset(dataset)
        self._add_returns_to_go()

    def _add_returns_to_go(self) -> None:
        """The replay buffer as a :class:`ReturnToGoReplayBuffer` (its arrays shared) under this model's rewards."""
        assert self.replay_buffer is not None
        self.replay_buffer = ReturnToGoReplayBuffer.from_replay_buffer(
            self.replay_buffer, self.gamma, self.reward_scale, self.reward_bias
        )

    def policy_values_in_logsumexp(
        self, q_policy: th.Tensor, replay_data: ReplayBufferSamples, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """``max(Q, G(s))``: the policy's values bounded below by the batch's returns-to-go."""
        returns_to_go = replay_data.returns_to_go  # type: ignore[attr-defined]
        logs.setdefault("train/cql_bound_rate", []).append((q_policy[0] < returns_to_go).float().mean().item())
        return th.maximum(q_policy, returns_to_go)
