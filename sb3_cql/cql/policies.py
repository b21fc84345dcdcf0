"""CQL's policies: SAC's actor and twin critics, with the two network passes CQL adds (:meth:`CQLCritic.forward_fused`,
:meth:`CQLActor.imitation_dist_params`); ``tests/test_cql.py`` checks each copy of SB3's rules against SB3's method."""

from __future__ import annotations

import torch as th
from stable_baselines3.common.policies import ContinuousCritic
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.sac import policies as sac_policies
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN, Actor, SACPolicy

from sb3_cql.common.policies import NormalizedFlatten, OfflinePolicy
from sb3_cql.cql.fused_mlp import relu_mlp, relu_mlp_parameters

__all__ = ["CQLActor", "CQLCritic", "CQLPolicy", "CnnPolicy", "MlpPolicy", "MultiInputPolicy", "NormalizedFlatten"]


class CQLCritic(ContinuousCritic):
    """SB3's ``ContinuousCritic`` with a fused pass for large batches (:meth:`forward_fused`)."""

    def forward_fused(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        """``forward(obs, actions)`` with the same gradients, each ReLU MLP Q-network as one fused node
        (:func:`~sb3_cql.cql.fused_mlp.relu_mlp`) on CPU tensors; SB3's ``forward`` otherwise. Also callable on any
        SB3 ``ContinuousCritic`` (``CQLCritic.forward_fused(critic, obs, actions)``)."""
        networks = [relu_mlp_parameters(q_net) for q_net in self.q_networks]
        sb3_forward = type(self).forward is ContinuousCritic.forward  # a critic with a forward of its own keeps it
        if not sb3_forward or actions.device.type != "cpu" or any(parameters is None for parameters in networks):
            return self(obs, actions)
        # SB3's rule (ContinuousCritic.forward): the features learn through the actor's loss when shared.
        with th.set_grad_enabled(not self.share_features_extractor):
            features = self.extract_features(obs, self.features_extractor)
        inputs = th.cat([features, actions], dim=1)
        return tuple(relu_mlp(inputs, parameters) for parameters in networks)  # type: ignore[arg-type]


class CQLActor(Actor):
    """SB3's SAC ``Actor`` with the warm start's distribution parameters (:meth:`imitation_dist_params`)."""

    def imitation_dist_params(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``get_action_dist_params(obs)``'s mean actions and log-std, the log-std head fed the shared layers' output
        detached. Also callable on any SAC ``Actor`` (``CQLActor.imitation_dist_params(actor, obs)``)."""
        features = self.extract_features(obs, self.features_extractor)
        latent_pi = self.latent_pi(features)
        log_std = th.clamp(self.log_std(latent_pi.detach()), LOG_STD_MIN, LOG_STD_MAX)
        return self.mu(latent_pi), log_std


class CQLPolicy(OfflinePolicy):
    """:class:`~sb3_cql.common.policies.OfflinePolicy` with :class:`CQLActor` and :class:`CQLCritic`: SAC's
    parameters, so a model saved with SAC's policy loads into it."""

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> CQLActor:
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return CQLActor(**actor_kwargs).to(self.device)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> CQLCritic:
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        return self.with_critic_layer_norm(CQLCritic(**critic_kwargs).to(self.device))


MlpPolicy = CQLPolicy


class CnnPolicy(CQLPolicy, sac_policies.CnnPolicy):
    """SAC's ``CnnPolicy`` (``NatureCNN`` features) with CQL's actor and critic."""


class MultiInputPolicy(CQLPolicy, sac_policies.MultiInputPolicy):
    """SAC's ``MultiInputPolicy`` (``CombinedExtractor`` features, Dict observations) with CQL's actor and critic."""


#: SAC's policy classes and CQL's for each: a model saved with one of SAC's loads into CQL's.
FROM_SAC = {SACPolicy: CQLPolicy, sac_policies.CnnPolicy: CnnPolicy, sac_policies.MultiInputPolicy: MultiInputPolicy}
