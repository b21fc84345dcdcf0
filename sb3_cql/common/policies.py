"""The offline algorithms' policies are SAC's (actor, twin critics), with an optional observation normaliser as
features extractor and optional action chunks (:class:`OfflinePolicy`)."""

from __future__ import annotations

import hashlib
import math
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.sac import policies as sac_policies
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

from sb3_cql.common.settings import check_finite_observation

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "NormalizedFlatten", "OfflinePolicy", "SACPolicy", "chunk_space"]


def chunk_space(action_space: spaces.Box, action_chunk: int) -> spaces.Box:
    """The space of ``action_chunk`` consecutive actions of ``action_space``, flattened: ``(action_chunk * dim,)``,
    the bounds tiled."""
    low, high = np.tile(action_space.low.ravel(), action_chunk), np.tile(action_space.high.ravel(), action_chunk)
    return spaces.Box(low, high, dtype=action_space.dtype)  # type: ignore[arg-type]


class OfflinePolicy(SACPolicy):
    """SAC's policy (``MlpPolicy``), optionally on chunks of ``action_chunk`` actions (Q-chunking, Li, Zhou and Levine
    2025, https://arxiv.org/abs/2507.07969): the actor emits the next ``action_chunk`` actions at once and the critics
    score the state with the whole chunk (both built on :func:`chunk_space`), while the policy's ``action_space``
    stays the env's.

    :meth:`predict` then runs each chunk open loop through SB3's ``state`` (passed back by ``evaluate_policy``,
    ``EvalCallback`` and the zoo's ``enjoy``, as for recurrent policies): a new chunk when one is used up, or at
    ``episode_start``. Without a state, each call starts a new chunk and returns its first action.

    With ``critic_layer_norm``, every hidden layer of the Q-networks is followed by a LayerNorm before its activation,
    as RLPD's critics (Ball et al. 2023), which keeps the values of states far from the data from diverging.

    With ``best_of_n`` > 1 the policy acts by ranking (SHARSA's best-of-N, Park et al. 2025): at each decision it draws
    ``best_of_n`` candidates from the actor's distribution and takes the one the critics value most
    (:meth:`best_of_n_actions`). With ``deterministic=True`` the candidates' noise is seeded by the observation's bytes,
    so the same observation gives the same action whatever came before (evaluations replay exactly).

    The policy acts with :attr:`acting_actor`, the trained actor unless a subclass keeps another (IQL's average of
    the actor's weights).

    :param action_chunk: actions per chunk (1: SAC's policy, one action a state).
    :param critic_layer_norm: LayerNorm after each hidden layer of the Q-networks.
    :param best_of_n: candidate actions ranked by the critics at each decision (1: the actor's own action).
    :param best_of_n_scale: the candidates' standard deviation as a multiple of the actor's (1: the actor's own
        distribution).
    :param args: SAC's ``SACPolicy`` arguments (``observation_space``, ``action_space``, ``lr_schedule``, ...).
    :param kwargs: SAC's ``SACPolicy`` keywords (``net_arch``, ...).
    """

    def __init__(
        self, *args: Any, action_chunk: int = 1, critic_layer_norm: bool = False, best_of_n: int = 1,
        best_of_n_scale: float = 1.0, **kwargs: Any,
    ) -> None:  # fmt: skip
        if action_chunk < 1:
            raise ValueError(f"action_chunk must be >= 1, got {action_chunk}")
        if best_of_n < 1:
            raise ValueError(f"best_of_n must be >= 1, got {best_of_n}")
        if not (best_of_n_scale > 0 and math.isfinite(best_of_n_scale)):
            raise ValueError(f"best_of_n_scale must be a finite number > 0, got {best_of_n_scale}")
        # Both read by _build, which SACPolicy's __init__ calls.
        self.action_chunk, self.critic_layer_norm = action_chunk, critic_layer_norm
        self.best_of_n, self.best_of_n_scale = best_of_n, best_of_n_scale
        super().__init__(*args, **kwargs)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> ContinuousCritic:
        return self.with_critic_layer_norm(super().make_critic(features_extractor))

    def with_critic_layer_norm(self, critic: ContinuousCritic) -> ContinuousCritic:
        """``critic`` with a LayerNorm after each hidden ``Linear`` of its Q-networks (with ``critic_layer_norm``)."""
        if not self.critic_layer_norm:
            return critic
        for index, q_net in enumerate(critic.q_networks):
            layers: list[nn.Module] = []
            for layer in q_net:
                layers.append(layer)
                if isinstance(layer, nn.Linear) and layer is not q_net[-1]:
                    layers.append(nn.LayerNorm(layer.out_features))
            normed = nn.Sequential(*layers).to(self.device)
            critic.add_module(f"qf{index}", normed)  # SB3's name of the network, so state dicts keep their keys' prefix
            critic.q_networks[index] = normed
        return critic

    def _build(self, lr_schedule: Schedule) -> None:
        if self.action_chunk > 1:
            chunks = chunk_space(self.action_space, self.action_chunk)  # type: ignore[arg-type]
            self.actor_kwargs["action_space"] = self.critic_kwargs["action_space"] = chunks
        super()._build(lr_schedule)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        names = ("action_chunk", "critic_layer_norm", "best_of_n", "best_of_n_scale")
        return {**super()._get_constructor_parameters(), **{name: getattr(self, name) for name in names}}

    @property
    def acting_actor(self) -> sac_policies.Actor:
        """The actor the policy acts with: :attr:`actor` unless a subclass overrides it."""
        return self.actor

    def _predict(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:
        if self.best_of_n == 1:
            return self.acting_actor(observation, deterministic)
        return self.best_of_n_actions(observation, self.best_of_n, deterministic)

    def best_of_n_actions(self, observation: th.Tensor | dict[str, th.Tensor], n: int, deterministic: bool) -> th.Tensor:
        """For each observation of the batch (tensors, as ``_predict`` receives them), the best of ``n``
        :meth:`candidate_actions` by the critics' value (the minimum of the twins): ``(batch, action_dim)`` in [-1, 1]
        (a whole chunk with action chunks). ``deterministic``: the noise from generators seeded by each observation's
        bytes, else from torch's global generator."""
        mean_actions, log_std, _ = self.acting_actor.get_action_dist_params(observation)
        log_std = log_std + math.log(self.best_of_n_scale)
        batch_size, action_dim = mean_actions.shape
        if deterministic:
            seeds = _observation_seeds(observation)
            noise = th.stack([th.randn(n, action_dim, generator=th.Generator().manual_seed(seed)) for seed in seeds])
            noise = noise.to(mean_actions.device).reshape(batch_size * n, action_dim)
        else:
            noise = th.randn(batch_size * n, action_dim, device=mean_actions.device)
        candidates = self.candidate_actions(mean_actions.repeat_interleave(n, 0), log_std.repeat_interleave(n, 0), noise)
        repeated = map_observations(lambda tensor: tensor.repeat_interleave(n, dim=0), observation)
        q_values = th.cat(self.critic(repeated, candidates), dim=1).min(dim=1).values.reshape(batch_size, n)
        best = q_values.argmax(dim=1)
        return candidates.reshape(batch_size, n, action_dim)[th.arange(batch_size, device=best.device), best]

    def candidate_actions(self, mean_actions: th.Tensor, log_std: th.Tensor, noise: th.Tensor) -> th.Tensor:
        """Actions of the actor's distribution for standard normal ``noise``: SAC's squashed Gaussian,
        ``tanh(mean + exp(log_std) * noise)``. A policy whose actor fits another distribution overrides it."""
        return th.tanh(mean_actions + log_std.exp() * noise)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """SB3's ``predict``; with action chunks, the next action of each env's chunk and the state to pass back
        (the chunks, ``(n_envs, action_chunk, *action_shape)``, and the next action's index in each). An observation
        with a NaN or an infinity is an :class:`~sb3_cql.common.settings.ObservationError` naming where it is."""
        check_finite_observation(observation)
        if self.action_chunk == 1:
            return super().predict(observation, state, episode_start, deterministic)
        _, vectorized = self.obs_to_tensor(observation)  # SB3's reading of a batch or one observation
        if not vectorized:  # one observation: a batch of one, to read SB3's (n * action_chunk, ...) actions as chunks
            observation = _batch_of_one(observation)
        n_envs = len(next(iter(observation.values()))) if isinstance(observation, dict) else len(observation)
        chunk_shape = (self.action_chunk, *self.action_space.shape)  # type: ignore[misc]
        if state is None:
            chunks, index = np.zeros((n_envs, *chunk_shape), dtype=np.float32), np.full(n_envs, self.action_chunk)
        else:
            chunks, index = state[0].copy(), state[1].copy()
        if episode_start is not None:
            index[np.asarray(episode_start, dtype=bool).reshape(n_envs)] = self.action_chunk
        new = index >= self.action_chunk
        if new.any():
            selected = {key: value[new] for key, value in observation.items()} if isinstance(observation, dict) else None
            actions, _ = super().predict(observation[new] if selected is None else selected, deterministic=deterministic)
            chunks[new] = actions.reshape(-1, *chunk_shape)
            index[new] = 0
        actions = chunks[np.arange(n_envs), index]
        index = index + 1
        return (actions if vectorized else actions[0]), (chunks, index)


def _observation_seeds(observation: th.Tensor | dict[str, th.Tensor]) -> list[int]:
    """A 63-bit seed per observation of the batch, from its bytes (of every key, for Dict observations)."""
    parts = [observation[key] for key in sorted(observation)] if isinstance(observation, dict) else [observation]
    rows = [part.detach().cpu().reshape(len(part), -1).numpy() for part in parts]
    seeds = []
    for index in range(len(rows[0])):
        digest = hashlib.blake2b(b"".join(row[index].tobytes() for row in rows), digest_size=8).digest()
        seeds.append(int.from_bytes(digest, "little") >> 1)
    return seeds


def map_observations(function: Any, observation: th.Tensor | dict[str, th.Tensor]) -> th.Tensor | dict[str, th.Tensor]:
    if isinstance(observation, dict):
        return {key: function(tensor) for key, tensor in observation.items()}
    return function(observation)


def _batch_of_one(observation: np.ndarray | dict[str, np.ndarray]) -> np.ndarray | dict[str, np.ndarray]:
    if isinstance(observation, dict):
        return {key: np.asarray(value)[None] for key, value in observation.items()}
    return np.asarray(observation)[None]


MlpPolicy = OfflinePolicy


class CnnPolicy(OfflinePolicy, sac_policies.CnnPolicy):
    """SAC's ``CnnPolicy`` (``NatureCNN`` features), optionally on action chunks."""


class MultiInputPolicy(OfflinePolicy, sac_policies.MultiInputPolicy):
    """SAC's ``MultiInputPolicy`` (``CombinedExtractor`` features, Dict observations), optionally on action chunks."""


#: SAC's policy classes and the offline algorithms' for each: a model saved with one of SAC's loads into ours.
FROM_SAC = {SACPolicy: OfflinePolicy, sac_policies.CnnPolicy: CnnPolicy, sac_policies.MultiInputPolicy: MultiInputPolicy}


class NormalizedFlatten(BaseFeaturesExtractor):
    """Flatten a Box observation and z-score it with fixed statistics (the dataset's, set by CQL): buffers of the
    module, saved and loaded with the policy's ``state_dict``; the identity (mean 0, std 1) until they are set."""

    def __init__(self, observation_space: spaces.Box) -> None:
        size = int(np.prod(observation_space.shape))
        super().__init__(observation_space, features_dim=size)
        self.register_buffer("mean", th.zeros(size))
        self.register_buffer("std", th.ones(size))

    def set_statistics(self, mean: np.ndarray, std: np.ndarray) -> None:
        """Use ``mean`` and ``std`` (flattened observation shape) from now on; a std below 1e-6 counts as 1e-6."""
        self.mean.copy_(th.as_tensor(mean, dtype=th.float32).reshape(-1))
        self.std.copy_(th.as_tensor(np.maximum(std, 1e-6), dtype=th.float32).reshape(-1))

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return (observations.flatten(start_dim=1) - self.mean) / self.std
