"""IQL's policies: SAC's actor and twin critics (:class:`~sb3_cql.common.policies.OfflinePolicy`) with a state-value
network (:class:`ValueNetwork`), and the actor's distribution as the references fit it (:class:`IQLActor`)."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.sac import policies as sac_policies
from stable_baselines3.sac.policies import Actor
from torch import nn

from sb3_cql.common.policies import NormalizedFlatten, OfflinePolicy

__all__ = ["CnnPolicy", "IQLActor", "IQLPolicy", "MlpPolicy", "MultiInputPolicy", "NormalizedFlatten", "ValueNetwork"]


class ValueNetwork(BaseModel):
    """The state value ``V(s)``: ``net_arch`` hidden layers (``activation_fn``; with ``layer_norm`` a LayerNorm before
    each activation, as the critics' with ``critic_layer_norm``) on the features of ``features_extractor`` (of
    ``features_dim``), one output. The other arguments are SB3's ``BaseModel``'s."""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.ReLU,
        layer_norm: bool = False,
        normalize_images: bool = True,
    ) -> None:
        super().__init__(observation_space, action_space, features_extractor=features_extractor,
                         normalize_images=normalize_images)  # fmt: skip
        layers = create_mlp(features_dim, 1, net_arch, activation_fn)
        if layer_norm:
            normed: list[nn.Module] = []
            for layer in layers:
                normed.append(layer)
                if isinstance(layer, nn.Linear) and layer is not layers[-1]:
                    normed.append(nn.LayerNorm(layer.out_features))
            layers = normed
        self.v_net = nn.Sequential(*layers)

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """``V(obs)``, ``(batch, 1)``."""
        return self.v_net(self.extract_features(obs, self.features_extractor))


#: The bounds of the IQL actor's log-std, d3rlpy's for IQL (ikostrikov/implicit_q_learning clips at the same).
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


class IQLActor(Actor):
    """SAC's ``Actor`` with the references' distribution for advantage-weighted regression: ``N(tanh(mu), std)``,
    samples clipped to [-1, 1], so data actions at the bounds keep a finite likelihood. ``std`` is one parameter per
    action dimension (``log_std_logits``, as d3rlpy's ``use_std_parameter``), ``log std = LOG_STD_MIN +
    sigmoid(logit) * (LOG_STD_MAX - LOG_STD_MIN)``: bounded with a gradient everywhere, unlike SAC's clamped head."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)  # (use_sde is refused by the offline base)
        del self.log_std  # SAC's head on the state
        self.log_std_logits = nn.Parameter(th.zeros(self.mu.out_features))

    def get_action_dist_params(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor, dict[str, th.Tensor]]:
        """``mu`` (before ``tanh``) at ``obs`` and the log-std, broadcast to it, as SAC's method returns them."""
        mean_actions = self.mu(self.latent_pi(self.extract_features(obs, self.features_extractor)))
        log_std = LOG_STD_MIN + th.sigmoid(self.log_std_logits) * (LOG_STD_MAX - LOG_STD_MIN)
        return mean_actions, log_std.expand_as(mean_actions), {}

    def log_prob_of(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """The log-density of ``actions`` (``(batch, action_dim)``, in [-1, 1]) at ``obs``, ``(batch,)``."""
        mean_actions, log_std, _ = self.get_action_dist_params(obs)
        distribution = th.distributions.Normal(th.tanh(mean_actions), log_std.exp())
        return distribution.log_prob(actions).sum(dim=-1)

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        mean_actions, log_std, _ = self.get_action_dist_params(obs)
        if deterministic:
            return th.tanh(mean_actions)
        return gaussian_actions(mean_actions, log_std, th.randn_like(mean_actions))


def gaussian_actions(mean_actions: th.Tensor, log_std: th.Tensor, noise: th.Tensor) -> th.Tensor:
    """Actions of ``N(tanh(mean_actions), exp(log_std))`` for standard normal ``noise``, clipped to [-1, 1]."""
    return (th.tanh(mean_actions) + log_std.exp() * noise).clamp(-1.0, 1.0)


class IQLPolicy(OfflinePolicy):
    """:class:`~sb3_cql.common.policies.OfflinePolicy` with :class:`IQLActor` and a :class:`ValueNetwork`
    (``value_net``, with its own optimizer at the critics' learning rate) of the critics' architecture.

    :param average_actor: also keep ``actor_average``, a copy of the actor without gradients that the policy acts with
        (:attr:`acting_actor`) and IQL's ``actor_average_tau`` moves towards the actor.
    """

    value_net: ValueNetwork
    actor_average: IQLActor | None

    def __init__(self, *args: Any, average_actor: bool = False, **kwargs: Any) -> None:
        self.average_actor = average_actor  # read by _build, which the base's __init__ calls
        super().__init__(*args, **kwargs)

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> IQLActor:
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return IQLActor(**actor_kwargs).to(self.device)

    def make_value_net(self) -> ValueNetwork:
        """A new :class:`ValueNetwork` on a features extractor of its own."""
        features_extractor = self.make_features_extractor()
        return ValueNetwork(
            self.observation_space,
            self.action_space,  # type: ignore[arg-type]
            net_arch=self.critic_kwargs["net_arch"],
            features_extractor=features_extractor,
            features_dim=features_extractor.features_dim,
            activation_fn=self.critic_kwargs["activation_fn"],
            layer_norm=self.critic_layer_norm,
            normalize_images=self.normalize_images,
        ).to(self.device)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        self.value_net = self.make_value_net()
        self.value_net.optimizer = self.optimizer_class(
            self.value_net.parameters(),
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )
        self.actor_average = None
        if self.average_actor:  # built last, so the other networks start as they would without it
            self.actor_average = self.make_actor()
            self.actor_average.load_state_dict(self.actor.state_dict())
            self.actor_average.requires_grad_(False)

    @property
    def acting_actor(self) -> IQLActor:
        """``actor_average`` with ``average_actor``, else the actor."""
        return self.actor if self.actor_average is None else self.actor_average

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "average_actor": self.average_actor}

    def load_state_dict(self, state_dict: Any, strict: bool = True, assign: bool = False) -> Any:
        """``nn.Module``'s; parameters saved without an average start the average as a copy of their actor."""
        if self.actor_average is not None and not any(key.startswith("actor_average.") for key in state_dict):
            average = {
                "actor_average." + key[len("actor.") :]: value for key, value in state_dict.items() if key.startswith("actor.")
            }
            state_dict = {**state_dict, **average}
        return super().load_state_dict(state_dict, strict, assign)

    def candidate_actions(self, mean_actions: th.Tensor, log_std: th.Tensor, noise: th.Tensor) -> th.Tensor:
        """Best-of-N's candidates from the distribution the actor fits (:class:`IQLActor`)."""
        return gaussian_actions(mean_actions, log_std, noise)

    def set_training_mode(self, mode: bool) -> None:
        super().set_training_mode(mode)
        self.value_net.set_training_mode(mode)
        if self.actor_average is not None:
            self.actor_average.set_training_mode(mode)


MlpPolicy = IQLPolicy


class CnnPolicy(IQLPolicy, sac_policies.CnnPolicy):
    """SAC's ``CnnPolicy`` (``NatureCNN`` features) with IQL's actor and value network."""


class MultiInputPolicy(IQLPolicy, sac_policies.MultiInputPolicy):
    """SAC's ``MultiInputPolicy`` (Dict observations) with IQL's actor and value network."""
