"""SAC's networks and replay buffer trained offline, from a dataset, and fine-tuned online with the dataset kept in the
buffer: the base of :class:`~sb3_cql.CQL`, :class:`~sb3_cql.IQL` and :class:`~sb3_cql.BC`."""

from __future__ import annotations

import contextlib
import inspect
import io
import json
import os
import time
import warnings
import zipfile
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_obs_shape
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, ReplayBufferSamples, Schedule
from stable_baselines3.common.utils import FloatSchedule
from stable_baselines3.common.vec_env import VecTransposeImage, unwrap_vec_wrapper
from torch.nn import functional as F

from sb3_cql.common.allocator import retain_freed_memory
from sb3_cql.common.atomic import check_saved_model, save_atomically
from sb3_cql.common.buffers import ActionChunkReplayBuffer, transposed_images, with_n_step_returns
from sb3_cql.common.finetune import OnlineFineTuning
from sb3_cql.common.policies import FROM_SAC, CnnPolicy, MlpPolicy, MultiInputPolicy, NormalizedFlatten, OfflinePolicy
from sb3_cql.common.settings import (
    SettingError,
    check_best_of_n,
    check_count,
    check_entropy,
    check_finite,
    check_fraction,
    check_keywords,
    check_net_arch,
    check_non_negative,
    check_rate,
    is_count,
    refuse_unsupported,
)
from sb3_cql.processes import interrupts_deferred

if TYPE_CHECKING:  # Minari loads with the data, the tasks with a standard dataset's collection: neither on import.
    from minari import MinariDataset

SelfOfflineSAC = TypeVar("SelfOfflineSAC", bound="OfflineSAC")


def behaviour_cloning_loss(mean_actions: th.Tensor, actions: th.Tensor) -> th.Tensor:
    """Mean squared error between a SAC actor's deterministic actions, ``tanh`` of its ``mean_actions`` (from
    ``Actor.get_action_dist_params``), and the data's ``actions`` (both in [-1, 1])."""
    return F.mse_loss(th.tanh(mean_actions), actions)


@contextlib.contextmanager
def frozen(module: th.nn.Module) -> Iterator[th.nn.Module]:
    """``module`` with its parameters out of autograd's graph while the block runs: an actor loss that reads the
    critics then back-propagates through them to the actions without computing the gradients of their weights, which
    no step would use (the critics' own step zeroes them first). The actor's gradients are unchanged."""
    parameters = [parameter for parameter in module.parameters() if parameter.requires_grad]
    for parameter in parameters:
        parameter.requires_grad_(False)
    try:
        yield module
    finally:
        for parameter in parameters:
            parameter.requires_grad_(True)


class OfflineSAC(OnlineFineTuning):
    """SAC's policies (actor, twin critics) and ``ReplayBuffer``, with the buffer filled from a dataset and
    :meth:`learn` making one gradient step per timestep without ever stepping the env (it gives the spaces;
    callbacks such as ``EvalCallback`` use their own envs). Subclasses write :meth:`train`.

    With ``online_fraction`` set, :meth:`learn` fine-tunes online instead: it is SAC's (``collect_rollouts`` in the
    env, then ``train``, with ``train_freq``, ``gradient_steps`` and ``learning_starts``), its timesteps are env steps,
    and the replay buffer is a :class:`~sb3_cql.common.MixedReplayBuffer`: the offline data stay, the new transitions
    go to an online part of ``online_buffer_size``, and every batch draws ``online_fraction`` of its samples from
    them. A model trained offline fine-tunes after ``load(path, env=env, online_fraction=0.5)``; its buffer
    (``save_replay_buffer``, checkpoints) holds the online transitions, and the offline data come back from the
    dataset id.

    :meth:`load` does not reload the data: a loaded model predicts with a one-transition buffer, and refills it from
    its dataset id when it trains again.

    A setting training cannot use (also one given to :meth:`load`), or a replay buffer given as ``dataset`` that
    holds a NaN, an infinity or an action outside [-1, 1] (SB3's buffers hold scaled actions), is a
    :class:`SettingError` naming the keyword and its value, raised when the model is set up; a keyword it does not
    take is a :class:`KeywordError` naming the closest one. :meth:`save` and :meth:`save_replay_buffer` leave a file
    whole or none. Ctrl-C during :meth:`learn` offline acts between gradient steps.

    :param policy: the policy model (``"MlpPolicy"``, ``"MultiInputPolicy"``: SAC's).
    :param env: the environment (for its spaces, and the default evaluation env).
    :param dataset: a Minari dataset, its id, or a filled ``ReplayBuffer`` (of finite values); ``None`` for an empty
        buffer of ``buffer_size`` (filled by hand, e.g. with :func:`sb3_cql.data.fill_replay_buffer`). A missing
        standard id (``sb3cql/Panda-v0/pid-v0``, ...) is collected first (:func:`sb3_cql.data.ensure_dataset`).
    :param learning_rate: learning rate of the critics and the entropy coefficient.
    :param actor_learning_rate: learning rate of the actor; ``None`` for ``learning_rate``.
    :param buffer_size: size of an empty replay buffer when ``dataset`` is ``None``.
    :param normalize_observations: z-score the observations with the dataset's mean and std inside the policy
        (:class:`~sb3_cql.common.policies.NormalizedFlatten` as its features extractor). ``None`` (the default): for an
        ``MlpPolicy`` on Box observations, without a ``features_extractor_class`` of the user's; ``True`` for any other
        policy is refused (a ``CnnPolicy`` scales its images by 255 itself, as SB3's).
    :param online_fraction: ``None`` to train offline; else fine-tune online, drawing this fraction of every batch
        from the online transitions (RLPD's symmetric sampling: 0.5).
    :param online_buffer_size: capacity of the online transitions when fine-tuning.
    :param learning_starts: env steps before the first gradient step, when fine-tuning (SAC's): the model's own
        rollouts (WSRL's warm-up), not SAC's uniform random actions.
    :param action_chunk: actions per decision (Q-chunking): the actor emits ``action_chunk`` actions at once, the
        critics score the state with the whole chunk, the TD target sums the chunk's rewards and bootstraps with
        ``gamma ** action_chunk`` (SB3's n-step returns over the chunk, ``n_steps = action_chunk``), the data are read
        as the chunk from every step (:class:`~sb3_cql.common.ActionChunkReplayBuffer`), and the chunk runs open loop
        when the model acts (:class:`~sb3_cql.common.policies.OfflinePolicy`). ``1`` (the default): one action a state.
    :param deterministic_rollouts: when fine-tuning, act with the policy's deterministic action plus ``action_noise``
        (TD3's exploration; SB3's ``NormalActionNoise``, or the zoo's ``noise_type``/``noise_std``) instead of a sample
        of the policy (SAC's). A clone's samples rarely hold a grasp where its deterministic action does
        (the documentation's *What we learned* page, *How a fine-tuned policy explores*).
    :param best_of_n: act by ranking: the policy draws ``best_of_n`` candidate actions (or chunks) from the actor at
        each decision and takes the one its critics value most (:class:`~sb3_cql.common.policies.OfflinePolicy`);
        saved with the model, so every evaluation acts that way; ``load(path, best_of_n=N)`` changes it. ``1`` (the
        default): the actor's own action.
    :param best_of_n_scale: the spread of best-of-N's candidates: their standard deviation is the actor's times
        ``best_of_n_scale`` (``0.1``: candidates near the actor's mean). Saved with the model, changed by
        ``load(path, best_of_n_scale=S)``. ``1`` (the default): samples of the actor's own distribution.
    :param reward_scale: the critics learn from ``reward_scale * reward + reward_bias`` (:meth:`critic_rewards`; the
        buffer keeps the data's rewards).
    :param reward_bias: see ``reward_scale``.
    :param kwargs: SAC's other arguments (``batch_size``, ``tau``, ``gamma``, ``action_noise``, ``seed``, ...).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    #: SAC's policy classes and ours for each: a model saved with one of SAC's loads into ours.
    policy_from_sac: ClassVar[dict[type[BasePolicy], type[BasePolicy]]] = FROM_SAC
    #: :meth:`save` and :meth:`save_replay_buffer` leave a file whole or none (the zoo plugin's test of a model).
    saves_atomically: ClassVar[bool] = True

    def __init__(
        self,
        policy: str | type[BasePolicy],
        env: GymEnv | str,
        dataset: MinariDataset | str | ReplayBuffer | None = None,
        learning_rate: float | Schedule = 3e-4,
        actor_learning_rate: float | Schedule | None = None,
        buffer_size: int = 2_000_000,
        normalize_observations: bool | None = None,
        online_fraction: float | None = None,
        online_buffer_size: int = 1_000_000,
        learning_starts: int = 0,
        deterministic_rollouts: bool = False,
        action_chunk: int = 1,
        best_of_n: int = 1,
        best_of_n_scale: float = 1.0,
        reward_scale: float = 1.0,
        reward_bias: float = 0.0,
        policy_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        refuse_unsupported(kwargs)
        check_keywords(type(self).__name__, kwargs, inspect.signature(SAC.__init__).parameters)
        check_count("action_chunk", action_chunk, 1)
        check_best_of_n(best_of_n)
        check_non_negative([("best_of_n_scale", best_of_n_scale)], strictly=True)
        self.best_of_n, self.best_of_n_scale = best_of_n, best_of_n_scale
        self.reward_scale, self.reward_bias = reward_scale, reward_bias
        if action_chunk > 1 and kwargs.get("n_steps", 1) not in (1, action_chunk):
            raise SettingError(f"n_steps={kwargs['n_steps']} with action_chunk={action_chunk}: a chunk's backup spans "
                               f"its {action_chunk} steps (n_steps is the chunk's length)")  # fmt: skip
        if action_chunk > 1 and kwargs.get("replay_buffer_class") is not None:
            raise SettingError("action_chunk > 1 samples from a replay buffer class of its own: leave replay_buffer_class out")
        self.action_chunk = action_chunk
        if action_chunk > 1:
            kwargs["n_steps"] = action_chunk
        self._sb3_chooses_buffer_class = kwargs.get("replay_buffer_class") is None
        self.dataset = dataset
        self.online_fraction = online_fraction
        self.online_buffer_size = online_buffer_size
        self.deterministic_rollouts = deterministic_rollouts
        self.actor_learning_rate = actor_learning_rate
        self._fill_on_setup = True  # load() turns it off: a loaded model does not reload its data
        self.data_sha256: str | None = None  # the digest of the offline transitions it first trained on
        policy_kwargs = dict(policy_kwargs or {})
        mlp = policy in ("MlpPolicy", self.policy_aliases["MlpPolicy"]) and "features_extractor_class" not in policy_kwargs
        if normalize_observations and not mlp:
            raise SettingError(
                "normalize_observations=True z-scores flat Box observations of an MlpPolicy with SB3's own features "
                f"(not {policy if isinstance(policy, str) else policy.__name__} or a features_extractor_class): leave it None"
            )
        if normalize_observations is None:
            normalize_observations = mlp
        self.normalize_observations = normalize_observations
        if normalize_observations:
            policy_kwargs["features_extractor_class"] = NormalizedFlatten
        if action_chunk > 1:
            policy_kwargs["action_chunk"] = action_chunk
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            # The dataset's own buffer replaces SB3's: allocate nothing here.
            buffer_size=1 if dataset is not None else buffer_size,
            learning_starts=learning_starts,
            policy_kwargs=policy_kwargs,
            **kwargs,
        )

    @classmethod
    def known_keywords(cls) -> set[str]:
        """The keywords the class takes: its own, and those it passes on to the classes above it (ours, then SAC's)."""
        known: set[str] = set()
        for klass in cls.__mro__:
            init = klass.__dict__.get("__init__")
            if init is None or klass is object:
                continue
            parameters = inspect.signature(init).parameters
            known.update(name for name, parameter in parameters.items() if parameter.kind is not parameter.VAR_KEYWORD)
            if not any(parameter.kind is parameter.VAR_KEYWORD for parameter in parameters.values()):
                break  # it passes nothing on
        return known - {"self"}

    @classmethod
    def refuse_unknown_keywords(cls, keywords: Iterable[str]) -> None:
        """:class:`KeywordError` naming those of ``keywords`` that the class does not take (the closest one with each):
        for callers that hold keywords before making the model (the zoo's hyperparameters, ``load``'s)."""
        check_keywords(cls.__name__, keywords, cls.known_keywords())

    def _check_settings(self) -> None:
        """:class:`SettingError` for a setting outside what training can use, where SB3 would train on without a word
        or fail later: run when the model is set up, so that ``load``'s keywords are checked too. Subclasses add theirs."""
        check_fraction("gamma", self.gamma)
        check_fraction("tau", self.tau, zero=True)  # 0: a target network that stays as it was made (SAC's too)
        check_rate("learning_rate", self.learning_rate)
        if self.actor_learning_rate is not None:
            check_rate("actor_learning_rate", self.actor_learning_rate)
        check_entropy(self.ent_coef, self.target_entropy)
        check_net_arch((self.policy_kwargs or {}).get("net_arch"))
        check_count("batch_size", self.batch_size, 1)
        check_count("learning_starts", self.learning_starts, 0)
        if self.gradient_steps != -1 and not is_count(self.gradient_steps, 0):
            raise SettingError(f"gradient_steps must be an integer >= 0, or -1 (as many as the env steps), "
                               f"got {self.gradient_steps!r}")  # fmt: skip
        check_count("train_freq", self.train_freq[0] if isinstance(self.train_freq, tuple) else self.train_freq, 1)
        check_count("target_update_interval", self.target_update_interval, 1)
        check_count("n_steps", self.n_steps, 1)
        check_count("buffer_size", self.buffer_size, 1)
        check_count("online_buffer_size", self.online_buffer_size, 1)
        check_count("action_chunk", self.action_chunk, 1)
        check_finite([("reward_scale", self.reward_scale), ("reward_bias", self.reward_bias)])
        if self.n_steps > 1 and self.reward_bias != 0 and self.gamma >= 1:
            raise SettingError("reward_bias with n_steps > 1 needs gamma < 1: the bias is summed over the steps of a sample")
        check_best_of_n(getattr(self, "best_of_n", 1))
        check_non_negative([("best_of_n_scale", getattr(self, "best_of_n_scale", 1.0))], strictly=True)
        fraction = self.online_fraction
        if fraction is not None and not (isinstance(fraction, (int, float)) and 0.0 <= fraction <= 1.0):
            raise SettingError(f"online_fraction must be None (offline training) or in [0, 1], got {fraction!r}")

    def _setup_model(self) -> None:
        self.algorithm = type(self).__name__  # saved with the model: load() reads it before the parameters
        self._check_settings()
        if isinstance(self.observation_space, spaces.Dict) and self.n_steps > 1:
            raise SettingError("n_steps > 1 is not supported with Dict observations (SB3's NStepReplayBuffer holds Box ones)")
        if getattr(self, "_sb3_chooses_buffer_class", True):
            # SB3 chose the buffer class (from n_steps and the observation space) and it was saved with the model: a
            # loaded model chooses again, for the n_steps given to load. Kept, SB3 would take it for a custom class that
            # leaves n_steps unused (and warn so, as SAC's load of an n-step model does).
            self.replay_buffer_class = None
            self.replay_buffer_kwargs = {k: v for k, v in self.replay_buffer_kwargs.items() if k not in ("n_steps", "gamma")}
        # A model saved with SAC's policy classes loads into ours (the same parameters).
        self.policy_class = self.policy_from_sac.get(self.policy_class, self.policy_class)  # type: ignore[arg-type]
        chunked, auto_entropy = getattr(self, "action_chunk", 1) > 1, self.target_entropy == "auto"
        for name, default, setting in (("best_of_n", 1, "best_of_n > 1"), ("best_of_n_scale", 1.0, "best_of_n_scale != 1")):
            value = getattr(self, name, default)
            if value != default or name in self.policy_kwargs:  # also a changed value given to load()
                if not issubclass(self.policy_class, OfflinePolicy):
                    raise SettingError(f"{setting} needs a policy of sb3_cql.common.policies (OfflinePolicy), "
                                       f"got {self.policy_class.__name__}")  # fmt: skip
                self.policy_kwargs[name] = value
        if chunked:
            if not issubclass(self.policy_class, OfflinePolicy):
                raise SettingError(f"action_chunk > 1 needs a policy of sb3_cql.common.policies (OfflinePolicy), "
                                   f"got {self.policy_class.__name__}")  # fmt: skip
            self.replay_buffer_class = ActionChunkReplayBuffer
            self.replay_buffer_kwargs.update(n_steps=self.action_chunk, gamma=self.gamma)
        with warnings.catch_warnings():
            # SB3 would warn that our chunk buffer, a custom class, leaves n_steps to it: it reads them.
            warnings.filterwarnings("ignore", message="`n_steps=.*custom `replay_buffer_class`", category=UserWarning)
            super()._setup_model()
        if chunked and auto_entropy:  # SAC's -|A| for an action is -|A| * action_chunk for a chunk
            self.target_entropy *= self.action_chunk
        rate = self.learning_rate if self.actor_learning_rate is None else self.actor_learning_rate
        self.actor_lr_schedule = FloatSchedule(rate)
        if self.dataset is not None and self._fill_on_setup:
            self._fill_from_dataset(self.dataset)
            self.dataset = self.dataset if isinstance(self.dataset, str) else None  # never pickle data into a model

    def _fill_from_dataset(self, dataset: MinariDataset | str | ReplayBuffer) -> None:
        """The replay buffer from ``dataset`` (:func:`sb3_cql.data.load_replay_buffer`; a buffer of the user's read as
        trained, :meth:`_read_as_trained`), then the observation statistics of ``normalize_observations``."""
        from sb3_cql.data.loading import load_replay_buffer  # (Minari loads with the data, not with the algorithms)

        buffer = load_replay_buffer(dataset, self.observation_space, self.action_space, self._data_observation_space(),
                                    self.device, self.replay_buffer_class, self.replay_buffer_kwargs)  # fmt: skip
        self._check_same_data(buffer, dataset)
        self.replay_buffer = self._read_as_trained(buffer) if buffer is dataset else buffer
        size = buffer.size()
        if self.normalize_observations and isinstance(self.actor.features_extractor, NormalizedFlatten):
            observations = self.replay_buffer.observations[:size].reshape(size, -1)
            mean, std = observations.mean(axis=0), observations.std(axis=0)
            for module in self.policy.modules():  # the actor's, the critics' and any other network's (IQL's value)
                if isinstance(module, NormalizedFlatten):
                    module.set_statistics(mean, std)

    def _check_same_data(self, buffer: ReplayBuffer, dataset: MinariDataset | str | ReplayBuffer) -> None:
        """Record the digest of the transitions the model first trains on (``data_sha256``, saved with it); warn, on one
        line, where a loaded model's data, reloaded from its dataset id, are not those: the same id collected on
        another machine can hold other arrays, and fine-tuning would mix those into its batches unseen."""
        from sb3_cql.data.digest import transitions_digest

        digest = transitions_digest(buffer)
        if self.data_sha256 is None:
            self.data_sha256 = digest
        elif digest != self.data_sha256:
            name = dataset if isinstance(dataset, str) else type(dataset).__name__
            warnings.warn(
                f"the offline data loaded from {name} (transitions sha256 {digest[:12]}) are not those this model was "
                f"trained on ({self.data_sha256[:12]}): it trains on these; to train on the same data, copy the dataset "
                "from where the model was trained (Minari's datasets folder)",
                UserWarning,
                stacklevel=2,
            )

    def _read_as_trained(self, buffer: ReplayBuffer) -> ReplayBuffer:
        """A buffer of the user's through the views this model trains with: images as the policy sees them, SB3's
        n-step returns (or action chunks) for ``n_steps`` > 1."""
        if buffer.obs_shape != get_obs_shape(self.observation_space):
            buffer = transposed_images(buffer, self.observation_space)
        chunks = self.replay_buffer_class if self.replay_buffer_class is ActionChunkReplayBuffer else NStepReplayBuffer
        return with_n_step_returns(buffer, self.n_steps, self.gamma, chunks)

    def _data_observation_space(self) -> spaces.Space:
        """The env's observation space as the data hold it: before SB3's ``VecTransposeImage``, which makes
        channel-last images channel-first for the policy (``self.observation_space``)."""
        transpose = None if self.env is None else unwrap_vec_wrapper(self.env, VecTransposeImage)
        return self.observation_space if transpose is None else transpose.venv.observation_space

    def learn(
        self: SelfOfflineSAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int | None = None,
        tb_log_name: str | None = None,
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfOfflineSAC:
        """Make ``total_timesteps`` gradient steps on the replay buffer, calling the callbacks after each one; with
        ``online_fraction`` set, fine-tune online for ``total_timesteps`` env steps instead (SAC's ``learn``).
        ``log_interval``: gradient steps between two dumps of the logs (offline, default 1000), or episodes (online,
        SAC's 4); ``tb_log_name`` by default the class's name."""
        # CPU torch slows down by 40x on denormal floats, which near-converged networks produce.
        th.set_flush_denormal(True)
        # Each step allocates and frees ~11 MB activations: keep that memory instead of page-faulting it back in.
        retain_freed_memory()
        tb_log_name = tb_log_name or type(self).__name__
        if self.online_fraction is not None:
            return self.learn_online(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
        log_interval = 1000 if log_interval is None else log_interval
        self._ensure_offline_data()
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        callback.on_training_start(locals(), globals())
        while self.num_timesteps < total_timesteps:
            with interrupts_deferred():  # Ctrl-C between gradient steps: a saved model is one after a whole step
                self.train(gradient_steps=1, batch_size=self.batch_size)
                self.num_timesteps += 1
            self._update_current_progress_remaining(self.num_timesteps, total_timesteps)
            callback.update_locals(locals())
            if not callback.on_step():
                break
            if log_interval > 0 and self.num_timesteps % log_interval == 0:
                self._dump_offline_logs()
        callback.on_training_end()
        return self

    def load_offline_data(self) -> ReplayBuffer:
        """The model's replay buffer as :meth:`learn` has it before training: a loaded model's refilled from its
        dataset id; one of a batch or more kept as it is.

        :raises SettingError: the buffer holds fewer than ``batch_size`` transitions and no dataset id says where
            to reload them from.
        """
        self._ensure_offline_data()
        assert self.replay_buffer is not None
        return self.replay_buffer

    def _ensure_offline_data(self) -> None:
        """Refill a loaded model's buffer from its dataset id; refuse a buffer smaller than one batch."""
        too_few = self.replay_buffer is None or self.replay_buffer.size() < self.batch_size
        if too_few and isinstance(self.dataset, str):  # a loaded model trains on its dataset again
            self._fill_from_dataset(self.dataset)
        elif type(self.replay_buffer) is ReplayBuffer:  # set by hand: read as the model reads its data
            self.replay_buffer = self._read_as_trained(self.replay_buffer)
        if self.replay_buffer is None or self.replay_buffer.size() < self.batch_size:
            size = 0 if self.replay_buffer is None else self.replay_buffer.size()
            hint = "" if isinstance(self.dataset, str) else " (a loaded model reloads them from its dataset id; none here)"
            raise SettingError(
                f"training needs batch_size={self.batch_size} offline transitions or more, the buffer has {size}{hint}"
            )

    def critic_rewards(self, replay_data: ReplayBufferSamples) -> th.Tensor:
        """The rewards the critics learn from, ``reward_scale * reward + reward_bias`` at every step; for an n-step
        sample (its ``discounts`` set) the bias is summed over the steps with their discounts, as the buffer sums the
        rewards: ``reward_scale * rewards + reward_bias * (1 - discounts) / (1 - gamma)``."""
        if replay_data.discounts is None or self.reward_bias == 0:  # (no sum of discounts: 0 / 0 with gamma 1)
            return self.reward_scale * replay_data.rewards + self.reward_bias
        steps = (1.0 - replay_data.discounts) / (1.0 - self.gamma)
        return self.reward_scale * replay_data.rewards + self.reward_bias * steps

    def _dump_offline_logs(self) -> None:
        elapsed = max(time.time_ns() - self.start_time, 1) / 1e9
        steps = self.num_timesteps - self._num_timesteps_at_start
        self.logger.record("time/gradient_steps_per_s", int(steps / elapsed))
        self.logger.record("time/time_elapsed", int(elapsed), exclude="tensorboard")
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(step=self.num_timesteps)

    def save(
        self,
        path: str | os.PathLike | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """SB3's, whole or not at all (:func:`~sb3_cql.common.atomic.save_atomically`): a save cut short leaves the
        file that was at ``path`` before, or none."""
        save_atomically(lambda target: super(OfflineSAC, self).save(target, exclude, include), path, "zip")

    def save_replay_buffer(self, path: str | os.PathLike | io.BufferedIOBase) -> None:
        """SB3's, whole or not at all, as :meth:`save` (``.pkl`` added to a path without a suffix). A fine-tuning
        model's :class:`MixedReplayBuffer` saves its online transitions only."""
        save_atomically(super().save_replay_buffer, path, "pkl")

    @classmethod
    def load(cls, path, env=None, device="auto", custom_objects=None, print_system_info=False, force_reset=True, **kwargs):
        """SB3's ``load``, without the training data: the replay buffer holds one transition (unless ``buffer_size``
        is given), so a loaded model predicts without allocating the training buffer. :meth:`learn` refills it from
        ``model.dataset`` when that names a dataset (or set ``model.replay_buffer`` by hand first)."""
        cls.refuse_unknown_keywords(kwargs)  # SB3 would set any keyword as an attribute, and train on without it
        check_saved_model(path)  # SB3: a KeyError for a missing member
        saved = saved_algorithm(path)
        if saved is not None and saved not in [klass.__name__ for klass in cls.__mro__]:
            article = "an" if saved[0] in "AEIOU" else "a"
            raise SettingError(f"{path} holds {article} {saved} model: load it with {saved}.load (in the zoo, --algo "
                               f"{saved.lower()})")  # fmt: skip
        kwargs.setdefault("buffer_size", 1)
        kwargs["_fill_on_setup"] = False
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "actor_lr_schedule", "_fill_on_setup"]


def saved_algorithm(path: Any) -> str | None:
    """The class that saved the model at ``path`` (a zip of SB3's, or a file object of one), as its ``algorithm``
    (or an older model's settings) tells; ``None`` where nothing tells."""
    try:
        if isinstance(path, (str, os.PathLike)):
            suffixed = path if os.path.exists(path) else f"{path}.zip"
            with zipfile.ZipFile(suffixed) as archive:
                data = json.loads(archive.read("data"))
        else:
            start = path.tell()
            try:
                with zipfile.ZipFile(path) as archive:
                    data = json.loads(archive.read("data"))
            finally:
                path.seek(start)
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, AttributeError):
        return None
    if "algorithm" in data:
        return str(data["algorithm"])
    if data.get("cql_calibrated"):
        return "CalQL"
    return "IQL" if "expectile" in data else "CQL" if "cql_alpha" in data else None
