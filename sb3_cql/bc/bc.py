"""Behaviour cloning: the actor of SAC regressed on a dataset's actions, the baseline of offline RL on expert data."""

from __future__ import annotations

import inspect
from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import update_learning_rate

from sb3_cql.common.offline import OfflineSAC, behaviour_cloning_loss
from sb3_cql.common.settings import KeywordError, SettingError, check_keywords

if TYPE_CHECKING:
    from minari import MinariDataset


class BC(OfflineSAC):
    """Behaviour cloning: SAC's actor trained offline to reproduce the dataset's actions (mean squared error of its
    deterministic action, :func:`~sb3_cql.common.behaviour_cloning_loss`), with no critic update. The model is a SAC
    model in every other respect (its critics untrained), so anything that evaluates or loads a SAC model takes it.

    :param policy: the policy model (``"MlpPolicy"``, ``"MultiInputPolicy"``: SAC's).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id, or a filled ``ReplayBuffer`` (see :class:`~sb3_cql.common.OfflineSAC`).
    :param min_return: filtered imitation: load only the episodes whose return is at least this (``1.0`` on the Panda
        tasks: the successful ones, :func:`sb3_cql.data.selection.select_episodes`); a Minari dataset or id only.
    :param top_fraction: filtered imitation: load only this share of the episodes (of those ``min_return`` keeps),
        those of the highest returns; a Minari dataset or id only.
    :param learning_rate: learning rate of the actor.
    :param buffer_size: size of an empty replay buffer when ``dataset`` is ``None``.
    :param batch_size: minibatch size of each gradient step.
    :param normalize_observations: z-score the observations with the dataset's mean and std inside the policy;
        ``None`` does for an ``MlpPolicy`` on Box observations (:class:`~sb3_cql.common.OfflineSAC`).
    :param action_chunk: actions per decision: the actor imitates the data's chunks, run open loop when it acts.
    :param replay_buffer_class: the class of the replay buffer the data load into (SAC's).
    :param replay_buffer_kwargs: keywords of that class (SAC's).
    :param optimize_memory_usage: SAC's; only ``False``.
    :param n_steps: SB3's n-step returns in the buffer's samples (BC reads only their observations and actions).
    :param stats_window_size: SAC's window of the rollout logs.
    :param tensorboard_log: TensorBoard log folder.
    :param policy_kwargs: keywords of the policy (``net_arch``, ...).
    :param verbose: 0 silent, 1 training logs, 2 debug.
    :param seed: seed of the random generators.
    :param device: torch device.
    :param _init_setup_model: build the networks now.
    :param sac_kwargs: none: SAC's keywords for what BC does not train (``gamma``, ``tau``, ...) are refused.
    """

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str,
        dataset: MinariDataset | str | ReplayBuffer | None = None,
        min_return: float | None = None,
        top_fraction: float | None = None,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 2_000_000,
        batch_size: int = 256,
        normalize_observations: bool | None = None,
        action_chunk: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        **sac_kwargs: Any,
    ) -> None:
        if sac_kwargs:
            _refuse_sac_keywords(sac_kwargs)
        self.min_return, self.top_fraction = min_return, top_fraction
        super().__init__(
            policy,
            env,
            dataset=dataset,
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            normalize_observations=normalize_observations,
            action_chunk=action_chunk,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            stats_window_size=stats_window_size,
            policy_kwargs=policy_kwargs,
            batch_size=batch_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=_init_setup_model,
        )

    def _check_settings(self) -> None:
        """OfflineSAC's checks, and the episode selection's."""
        super()._check_settings()
        if self.min_return is None and self.top_fraction is None:
            return
        from sb3_cql.data.selection import check_selection  # (the data package loads Minari: only when selecting)

        problem = check_selection(self.min_return, self.top_fraction)
        if problem is not None:
            raise SettingError(problem)
        if self.dataset is not None and not isinstance(self.dataset, str) and not _is_minari(self.dataset):
            raise SettingError("min_return and top_fraction select episodes of a Minari dataset (or id): a replay buffer "
                               "has no episodes to select; filter the data before filling it")  # fmt: skip

    def _fill_from_dataset(self, dataset: MinariDataset | str | ReplayBuffer) -> None:
        """OfflineSAC's, with only the episodes ``min_return`` and ``top_fraction`` select."""
        if self.min_return is None and self.top_fraction is None:
            return super()._fill_from_dataset(dataset)
        from sb3_cql.data.loading import resolve_dataset
        from sb3_cql.data.selection import select_episodes

        dataset = resolve_dataset(dataset)
        try:
            selected = select_episodes(dataset, self.min_return, self.top_fraction)  # type: ignore[arg-type]
        except ValueError as error:
            raise SettingError(str(error)) from None
        if self.verbose >= 1:
            print(f"BC imitates {selected.total_episodes} of the {dataset.total_episodes} episodes of "  # type: ignore[union-attr]
                  f"{dataset.spec.dataset_id} (min_return={self.min_return}, top_fraction={self.top_fraction})")  # type: ignore[union-attr]  # fmt: skip
        return super()._fill_from_dataset(selected)

    @classmethod
    def known_keywords(cls) -> set[str]:
        """BC's own keywords: it refuses SAC's others (no critic, no entropy, no online fine-tuning)."""
        return set(inspect.signature(cls.__init__).parameters) - {"self", "sac_kwargs"}

    @classmethod
    def refuse_unknown_keywords(cls, keywords: Any) -> None:
        """Refuse keywords as BC's constructor does."""
        unknown = {keyword: None for keyword in keywords if keyword not in cls.known_keywords()}
        if unknown:
            _refuse_sac_keywords(unknown)

    def train(self, gradient_steps: int, batch_size: int = 256) -> None:
        """``gradient_steps`` Adam steps on the behaviour-cloning loss of the actor."""
        self.policy.set_training_mode(True)
        update_learning_rate(self.actor.optimizer, self.actor_lr_schedule(self._current_progress_remaining))
        losses = []
        for _ in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            mean_actions, _, _ = self.actor.get_action_dist_params(data.observations)
            loss = behaviour_cloning_loss(mean_actions, data.actions)
            self.actor.optimizer.zero_grad()
            loss.backward()
            self.actor.optimizer.step()
            losses.append(loss.item())
            self._n_updates += 1
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/actor_loss", float(np.mean(losses)))


def _refuse_sac_keywords(keywords: dict[str, Any]) -> None:
    """One line for keywords BC does not take: SAC's that configure what BC does not train, or unknown ones."""
    sac = set(inspect.signature(SAC.__init__).parameters)
    names = ", ".join(sorted(keywords))
    if set(keywords) <= sac:
        raise KeywordError(f"BC does not take {names}: BC trains its actor on the data's actions, without SAC's critics, "
                        f"entropy coefficient or interaction with the env (CQL takes them)")  # fmt: skip
    check_keywords("BC", keywords, inspect.signature(BC.__init__).parameters)


def _is_minari(dataset: Any) -> bool:
    return type(dataset).__name__ == "MinariDataset"  # (a check that does not import Minari)
