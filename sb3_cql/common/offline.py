"""SAC's networks and replay buffer trained offline, from a dataset, and fine-tuned online with the dataset kept in the
buffer: the base of :class:`~sb3_cql.CQL` and :class:`~sb3_cql.BC`."""

from __future__ import annotations

import inspect
import io
import numbers
import os
import time
import warnings
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_obs_shape
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import FloatSchedule
from stable_baselines3.common.vec_env import VecTransposeImage, unwrap_vec_wrapper
from torch.nn import functional as F

from sb3_cql.common.allocator import retain_freed_memory
from sb3_cql.common.atomic import save_atomically
from sb3_cql.common.buffers import (
    ActionChunkReplayBuffer,
    MixedReplayBuffer,
    ReturnToGoReplayBuffer,
    transposed_images,
    with_n_step_returns,
)
from sb3_cql.common.policies import FROM_SAC, CnnPolicy, MlpPolicy, MultiInputPolicy, NormalizedFlatten, OfflinePolicy
from sb3_cql.processes import interrupts_deferred

if TYPE_CHECKING:  # Minari loads with the data, the tasks with a standard dataset's collection: neither on import.
    from minari import MinariDataset

SelfOfflineSAC = TypeVar("SelfOfflineSAC", bound="OfflineSAC")


class SettingError(ValueError):
    """A keyword argument of an offline algorithm (given to its constructor or to ``load``) that it cannot train with,
    or a replay buffer given as its ``dataset`` that it cannot train on; the message names the keyword and the value."""


class KeywordError(SettingError, TypeError):
    """A keyword argument an offline algorithm does not take: a misspelt one, or SAC's for what it does not train. A
    ``TypeError`` too, as Python's own for an unexpected keyword."""


def check_keywords(algorithm: str, given: Iterable[str], known: Iterable[str]) -> None:
    """:class:`KeywordError` naming the keywords of ``given`` that are not ``known``, each with the known one it is
    closest to."""
    import difflib

    known = sorted(known)
    unknown = sorted(set(given) - set(known))
    if unknown:
        guesses = [f"{name} (did you mean {close[0]}?)" if (close := difflib.get_close_matches(name, known, 1)) else name
                   for name in unknown]  # fmt: skip
        raise KeywordError(f"{algorithm} got unexpected keyword arguments: {', '.join(guesses)}")


def is_count(value: Any, minimum: int) -> bool:
    """Whether ``value`` is an integer (not a bool) of at least ``minimum``."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= minimum


def check_count(name: str, value: Any, minimum: int) -> None:
    """:class:`SettingError` unless the setting ``name`` is an integer of at least ``minimum``."""
    if not is_count(value, minimum):
        raise SettingError(f"{name} must be an integer >= {minimum}, got {value!r}")


def check_fraction(name: str, value: Any, zero: bool = False) -> None:
    """:class:`SettingError` unless the setting ``name`` is a number in (0, 1] (in [0, 1] with ``zero``)."""
    number = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not (number and (value >= 0 if zero else value > 0) and value <= 1):
        raise SettingError(f"{name} must be in {'[' if zero else '('}0, 1], got {value!r}")


def check_non_negative(names_values: Iterable[tuple[str, Any]], strictly: bool = False) -> None:
    """:class:`SettingError` unless each setting is a number >= 0 (> 0 with ``strictly``)."""
    for name, value in names_values:
        number = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if not number or not (value > 0 if strictly else value >= 0):
            raise SettingError(f"{name} must be a number {'>' if strictly else '>='} 0, got {value!r}")
        if not np.isfinite(value):
            raise SettingError(f"{name} must be a finite number, got {value!r}")


def check_finite(names_values: Iterable[tuple[str, Any]]) -> None:
    """:class:`SettingError` unless each setting is a finite number."""
    for name, value in names_values:
        if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and np.isfinite(value)):
            raise SettingError(f"{name} must be a finite number, got {value!r}")


def check_rate(name: str, value: Any) -> None:
    """:class:`SettingError` unless the learning rate ``name`` is a finite number >= 0, or a schedule (a callable of the
    progress remaining, as SB3's) whose first value is. 0 is SB3's frozen network, which the zoo's ``enjoy`` and
    ``record_video`` load models with."""
    if callable(value) and not isinstance(value, numbers.Real):
        try:
            first = value(1.0)
        except Exception as error:
            raise SettingError(f"{name}: the schedule {value!r} fails at progress 1.0: {error}") from None
        if not (isinstance(first, numbers.Real) and np.isfinite(first) and first >= 0):
            raise SettingError(f"{name} must be a number >= 0, got a schedule starting at {first!r}")
        return
    check_non_negative([(name, value)])


def check_net_arch(net_arch: Any) -> None:
    """:class:`SettingError` unless ``net_arch`` (a policy keyword) is SB3's: ``None``, a list of layer sizes (integers
    >= 1), or a dict of such lists (``pi``, ``qf``)."""
    layers = net_arch.values() if isinstance(net_arch, dict) else [net_arch]
    for sizes in layers:
        if sizes is not None and not (isinstance(sizes, (list, tuple)) and all(is_count(size, 1) for size in sizes)):
            raise SettingError(f"net_arch must be a list of layer sizes (integers >= 1) or a dict of them, got {net_arch!r}")


def check_entropy(ent_coef: Any, target_entropy: Any) -> None:
    """:class:`SettingError` unless SAC's ``ent_coef`` is a finite number >= 0, ``\"auto\"`` or ``\"auto_X\"`` (X > 0, its
    initial value), and ``target_entropy`` is ``\"auto\"`` or a finite number."""
    if isinstance(ent_coef, str):
        initial = ent_coef.partition("_")[2] if ent_coef.startswith("auto_") else "1" if ent_coef == "auto" else ""
        try:
            valid = np.isfinite(float(initial)) and float(initial) > 0
        except ValueError:
            valid = False
        if not valid:
            raise SettingError(f"ent_coef must be a finite number >= 0, 'auto' or 'auto_X' with X > 0, got {ent_coef!r}")
    else:
        check_non_negative([("ent_coef", ent_coef)])
    if not (isinstance(target_entropy, str) and target_entropy == "auto"):
        check_finite([("target_entropy", target_entropy)])


def first_non_finite(buffer: ReplayBuffer) -> tuple[str, int, int, float] | None:
    """The first NaN or infinity among the filled transitions of ``buffer``: ``(field, index, env, value)``, the
    field (``observations['key']`` for a dict of them), the buffer index and env of its transition; ``None`` if all
    are finite."""
    size = buffer.size()
    fields = []
    for name in ("observations", "next_observations"):
        array = getattr(buffer, name, None)
        items = array.items() if isinstance(array, dict) else [(None, array)]
        fields += [(name if key is None else f"{name}[{key!r}]", values) for key, values in items]
    fields += [("actions", buffer.actions), ("rewards", buffer.rewards)]
    for name, values in fields:
        if values is None or not np.issubdtype(values.dtype, np.floating):
            continue
        filled = values[:size].reshape(size, buffer.n_envs, -1)
        bad = np.argwhere(~np.isfinite(filled))
        if len(bad):
            index, env, element = bad[0]
            return name, int(index), int(env), float(filled[index, env, element])
    return None


#: How far a buffer's scaled action may lie outside [-1, 1] (float32 rounding of data scaled elsewhere).
SCALED_ACTION_TOLERANCE = 1e-5


def first_action_outside(buffer: ReplayBuffer) -> tuple[int, int, int, float] | None:
    """The first action among the filled transitions of ``buffer`` outside [-1, 1], the scaled action space SB3's
    buffers hold (``policy.scale_action``): ``(index, env, component, value)``; ``None`` if all lie inside (NaN
    compares as inside: :func:`first_non_finite` finds it)."""
    size = buffer.size()
    filled = buffer.actions[:size].reshape(size, buffer.n_envs, -1)
    bad = np.argwhere(np.abs(filled) > 1.0 + SCALED_ACTION_TOLERANCE)
    if not len(bad):
        return None
    index, env, component = bad[0]
    return int(index), int(env), int(component), float(filled[index, env, component])


class TrainingDivergedError(FloatingPointError, ValueError):
    """A training loss became NaN or infinite. A ``ValueError`` too, so that RL-Zoo3's tuning prunes the trial
    (it prunes on ``ValueError``) instead of ending the whole study."""


def finite_loss_value(loss: th.Tensor, description: str, step: int, hint: str) -> float:
    """``loss`` as a number; :class:`TrainingDivergedError` naming ``description`` (``"CQL's critic loss"``), the
    gradient ``step`` and a ``hint`` of what to try if it is NaN or infinite."""
    value = loss.item()
    if not np.isfinite(value):
        raise TrainingDivergedError(f"{description} is {value} at gradient step {step}: training diverged ({hint})")
    return value


def shaped_rewards(replay_data: Any, reward_scale: float, reward_bias: float, gamma: float) -> th.Tensor:
    """The rewards a critic learns from, ``reward_scale * reward + reward_bias`` at every step; for an n-step sample
    (its ``discounts`` set) the bias is summed over the steps with their discounts, as the buffer sums the rewards:
    ``reward_scale * rewards + reward_bias * (1 - discounts) / (1 - gamma)``."""
    if replay_data.discounts is None:
        return reward_scale * replay_data.rewards + reward_bias
    steps_discount = (1.0 - replay_data.discounts) / (1.0 - gamma)
    return reward_scale * replay_data.rewards + reward_bias * steps_discount


def behaviour_cloning_loss(mean_actions: th.Tensor, actions: th.Tensor) -> th.Tensor:
    """Mean squared error between a SAC actor's deterministic actions, ``tanh`` of its ``mean_actions`` (from
    ``Actor.get_action_dist_params``), and the data's ``actions`` (both in [-1, 1])."""
    return F.mse_loss(th.tanh(mean_actions), actions)


class OfflineSAC(SAC):
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

    Observations are z-scored with the dataset's statistics (``normalize_observations``) inside the policy, so
    ``predict`` applies the same normalisation after ``save``/``load``. :meth:`load` does not reload the data: a
    loaded model predicts with a one-transition buffer, and refills it from its dataset id when it trains again.

    A setting training cannot use (``gamma`` or ``tau`` outside [0, 1], a learning rate that is not a finite number
    >= 0, a negative ``ent_coef``, a NaN ``target_entropy``, a layer of 0 units, a negative step count, a ``batch_size``
    below 1, ...; also one given to :meth:`load`) is a :class:`SettingError` naming the keyword and its value, raised
    when the model is set up, and so is a replay buffer given as ``dataset`` that holds a NaN or an infinity, or an
    action outside [-1, 1] (SB3's buffers hold actions scaled by ``policy.scale_action``); a keyword it does not take
    is a :class:`KeywordError` naming the closest one. :meth:`save` and :meth:`save_replay_buffer` leave a file whole
    or none. Ctrl-C during :meth:`learn` offline acts between gradient steps: the model is the one
    after its last whole step.

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
    :param learning_starts: env steps of random actions before training starts, when fine-tuning (SAC's).
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
        policy_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        _refuse_unsupported(kwargs)
        check_keywords(type(self).__name__, kwargs, inspect.signature(SAC.__init__).parameters)
        check_count("action_chunk", action_chunk, 1)
        check_count("best_of_n", best_of_n, 1)
        check_non_negative([("best_of_n_scale", best_of_n_scale)], strictly=True)
        self.best_of_n, self.best_of_n_scale = best_of_n, best_of_n_scale
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
    def refuse_unknown_keywords(cls, keywords: Iterable[str]) -> None:
        """:class:`KeywordError` naming those of ``keywords`` that the class does not take (the closest one with each):
        for callers that hold keywords before making the model (the zoo's hyperparameters)."""
        parameters = inspect.signature(cls.__init__).parameters
        takes_more = any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values())
        sac = inspect.signature(SAC.__init__).parameters if takes_more else {}
        check_keywords(cls.__name__, keywords, [*parameters, *sac])

    def _check_settings(self) -> None:
        """:class:`SettingError` for a setting outside what training can use, where SB3 would train on without a word
        or fail later with another message: run when the model is set up, so that it checks the keywords given to
        ``load`` (a fine-tuning's) too. Subclasses add theirs."""
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
        check_count("best_of_n", getattr(self, "best_of_n", 1), 1)
        check_non_negative([("best_of_n_scale", getattr(self, "best_of_n_scale", 1.0))], strictly=True)
        fraction = self.online_fraction
        if fraction is not None and not (isinstance(fraction, numbers.Real) and 0.0 <= fraction <= 1.0):
            raise SettingError(f"online_fraction must be None (offline training) or in [0, 1], got {fraction!r}")

    def _setup_model(self) -> None:
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
        """The replay buffer from ``dataset``: a given buffer as it is (viewed with SB3's n-step returns for
        ``n_steps`` > 1), a Minari dataset (or id, collected first if it is a missing standard one) loaded into a buffer
        of ``replay_buffer_class`` (SB3's choice: ``NStepReplayBuffer`` for ``n_steps`` > 1); then the observation
        statistics of ``normalize_observations``."""
        data_space = self._data_observation_space()
        if isinstance(dataset, ReplayBuffer):
            fits = dataset.obs_shape in (get_obs_shape(self.observation_space), get_obs_shape(data_space))
            if not fits or dataset.action_dim != self.action_space.shape[0]:
                raise SettingError(
                    f"dataset: the replay buffer's observations {dataset.obs_shape} and actions ({dataset.action_dim},) "
                    f"do not match the env's {get_obs_shape(data_space)} and {self.action_space.shape}"
                )
            non_finite = first_non_finite(dataset)
            if non_finite is not None:  # it would train on as a NaN loss, or a distribution torch refuses
                field, index, env, value = non_finite
                at = f"index {index}" + (f", env {env}" if dataset.n_envs > 1 else "")
                raise SettingError(f"dataset: the replay buffer's {field} hold {value} at {at}: every value must be "
                                   "finite")  # fmt: skip
            outside = first_action_outside(dataset)
            if outside is not None:  # SB3 stores actions scaled to the policy's [-1, 1]; a tanh policy never reaches them
                index, env, component, value = outside
                at = f"index {index}" + (f", env {env}" if dataset.n_envs > 1 else "")
                raise SettingError(f"dataset: the replay buffer's actions hold {value:g} at {at} (action[{component}]), "
                                   "outside [-1, 1]: store actions scaled as SB3 does (policy.scale_action)")  # fmt: skip
            if dataset.obs_shape != get_obs_shape(self.observation_space):
                dataset = transposed_images(dataset, self.observation_space)
            chunks = self.replay_buffer_class if self.replay_buffer_class is ActionChunkReplayBuffer else NStepReplayBuffer
            self.replay_buffer = with_n_step_returns(dataset, self.n_steps, self.gamma, chunks)
        else:
            from sb3_cql.data.replay import fill_replay_buffer

            if isinstance(dataset, str):
                from sb3_cql.data.collection import ensure_dataset  # the tasks load only to collect a standard dataset

                dataset = ensure_dataset(dataset)
            self.replay_buffer = fill_replay_buffer(
                dataset,
                data_space,
                self.action_space,
                device=self.device,
                replay_buffer_class=self.replay_buffer_class,
                replay_buffer_kwargs=self.replay_buffer_kwargs,
                buffer_observation_space=self.observation_space,
            )
        size = self.replay_buffer.size()
        if size == 0:
            raise SettingError("the dataset holds no transitions")
        if self.normalize_observations and isinstance(self.actor.features_extractor, NormalizedFlatten):
            observations = self.replay_buffer.observations[:size].reshape(size, -1)
            mean, std = observations.mean(axis=0), observations.std(axis=0)
            for module in self.policy.modules():  # the actor's, the critics' and any other network's (IQL's value)
                if isinstance(module, NormalizedFlatten):
                    module.set_statistics(mean, std)

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

        :param total_timesteps: gradient steps (offline) or env steps (online).
        :param callback: SB3 callback(s), called once per gradient step (offline) or env step (online).
        :param log_interval: gradient steps between two dumps of the logs (offline, default 1000), or episodes
            (online, default SAC's 4).
        :param tb_log_name: name of the TensorBoard run; by default the algorithm's class name (``CQL``, ``BC``).
        :param reset_num_timesteps: count from 0 (else continue the count of a previous ``learn``).
        :param progress_bar: show a progress bar of the steps.
        """
        # CPU torch slows down by 40x on denormal floats, which near-converged networks produce.
        th.set_flush_denormal(True)
        # Each step allocates and frees ~11 MB activations: keep that memory instead of page-faulting it back in.
        retain_freed_memory()
        tb_log_name = tb_log_name or type(self).__name__
        if self.online_fraction is not None:
            self._prepare_online_buffer(reset_num_timesteps)
            # Chunks run open loop from the first step: SB3's learn starts (or continues) with a new one (and resets
            # the action noise: a HeldActionNoise draws afresh with the chunk).
            self._rollout_chunks, self._rollout_episode_starts = None, np.ones(self.n_envs, dtype=bool)
            log_interval = 4 if log_interval is None else log_interval
            return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
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

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """SAC's exploration (a sample of the policy, plus ``action_noise`` if any), or with ``deterministic_rollouts``
        TD3's: the deterministic action plus ``action_noise``, clipped to the action space (after ``learning_starts``;
        the random warm-up stays SB3's). With action chunks, each chunk (a sample, or the deterministic chunk) runs open
        loop through the policy's ``state``, a new one when it is used up or an episode ends."""
        chunked = self.action_chunk > 1
        if (not self.deterministic_rollouts and not chunked) or self.num_timesteps < learning_starts:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        assert self._last_obs is not None
        if chunked:
            action, self._rollout_chunks = self.policy.predict(
                self._last_obs, self._rollout_chunks, self._rollout_episode_starts, deterministic=self.deterministic_rollouts
            )
            self._rollout_episode_starts = np.zeros(n_envs, dtype=bool)
        else:
            action, _ = self.predict(self._last_obs, deterministic=True)
        scaled_action = self.policy.scale_action(action)
        if action_noise is not None:
            scaled_action = np.clip(scaled_action + action_noise(), -1, 1)
        return self.policy.unscale_action(scaled_action), scaled_action

    def _store_transition(self, replay_buffer: ReplayBuffer, buffer_action: np.ndarray, new_obs: Any,
                          reward: np.ndarray, dones: np.ndarray, infos: list[dict[str, Any]]) -> None:  # fmt: skip
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        if self.action_chunk > 1:  # an episode that ended starts the next with a new chunk
            self._rollout_episode_starts = self._rollout_episode_starts | np.asarray(dones, dtype=bool)

    def load_offline_data(self) -> ReplayBuffer:
        """The model's offline data, in its replay buffer, as :meth:`learn` has them before training: a loaded model
        (whose buffer :meth:`load` leaves at one transition) refills it from its dataset id, collecting a missing
        standard dataset first; a buffer of one batch or more is kept as it is.

        :return: the replay buffer (``model.replay_buffer``).
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
        if self.replay_buffer is None or self.replay_buffer.size() < self.batch_size:
            size = 0 if self.replay_buffer is None else self.replay_buffer.size()
            hint = "" if isinstance(self.dataset, str) else " (a loaded model reloads them from its dataset id; none here)"
            raise SettingError(
                f"training needs batch_size={self.batch_size} offline transitions or more, the buffer has {size}{hint}"
            )

    def _prepare_online_buffer(self, reset_num_timesteps: bool) -> None:
        """Make the replay buffer a :class:`MixedReplayBuffer`: the offline data (the buffer's, or reloaded from the
        dataset id, also under a loaded buffer of online transitions) and an online part of ``online_buffer_size``."""
        mixed = self.replay_buffer if isinstance(self.replay_buffer, MixedReplayBuffer) else None
        if mixed is None:
            self._ensure_offline_data()
            offline = self.replay_buffer
            assert offline is not None
            mixed = MixedReplayBuffer(offline, self._empty_buffer_like(offline), self.online_fraction)
        elif mixed.offline is None:  # a loaded buffer of online transitions: the offline data come from the dataset
            self.replay_buffer = None
            try:
                self._ensure_offline_data()
                offline = self.replay_buffer
            finally:
                self.replay_buffer = mixed  # kept, also when the data cannot be loaded
            mixed.set_offline(offline)
        mixed.online_fraction = self.online_fraction  # a fraction given to load() applies to a loaded buffer too
        self.replay_buffer = mixed
        if reset_num_timesteps or self._last_obs is None:  # SB3's learn resets the env: a new episode starts
            mixed.start_new_episodes()

    def _empty_buffer_like(self, buffer: ReplayBuffer) -> ReplayBuffer:
        """An empty buffer of ``online_buffer_size`` of ``buffer``'s class and settings, for this model's env."""
        kwargs: dict[str, Any] = {}
        if isinstance(buffer, NStepReplayBuffer):
            kwargs = {"gamma": buffer.gamma, "n_steps": buffer.n_steps}
        if isinstance(buffer, ReturnToGoReplayBuffer):
            kwargs.update(reward_scale=buffer.reward_scale, reward_bias=buffer.reward_bias)
        return type(buffer)(
            self.online_buffer_size,
            self.observation_space,
            self.action_space,
            device=self.device,
            n_envs=self.n_envs,
            handle_timeout_termination=True,
            **kwargs,
        )

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
        """SB3's, whole or not at all (:func:`~sb3_cql.common.atomic.save_atomically`): a save cut short (an error,
        Ctrl-C, ``kill -9``) leaves the file that was at ``path`` before, or none. ``path`` without a suffix gets
        ``.zip``, as SB3's; a file object is written as SB3 writes it.

        :param path: where to save the model.
        :param exclude: attributes not to save, besides SB3's own exclusions.
        :param include: attributes to save although excluded.
        """
        save_atomically(lambda target: super(OfflineSAC, self).save(target, exclude, include), path, "zip")

    def save_replay_buffer(self, path: str | os.PathLike | io.BufferedIOBase) -> None:
        """SB3's, whole or not at all, as :meth:`save` (``.pkl`` added to a path without a suffix). A fine-tuning
        model's :class:`MixedReplayBuffer` saves its online transitions only."""
        save_atomically(super().save_replay_buffer, path, "pkl")

    def load_replay_buffer(self, path: str | os.PathLike | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """SB3's. A fine-tuning buffer comes back with its online transitions only: the offline data this model holds
        stay under it (else :meth:`learn` reloads them from the dataset id)."""
        offline = self.replay_buffer.offline if isinstance(self.replay_buffer, MixedReplayBuffer) else self.replay_buffer
        super().load_replay_buffer(path, truncate_last_traj)
        loaded = self.replay_buffer
        keeps = offline is not None and offline.size() >= self.batch_size
        if isinstance(loaded, MixedReplayBuffer) and loaded.offline is None and keeps and type(offline) is type(loaded.online):
            loaded.set_offline(offline)

    @classmethod
    def load(cls, path, env=None, device="auto", custom_objects=None, print_system_info=False, force_reset=True, **kwargs):
        """SB3's ``load``, without the training data: the replay buffer holds one transition (unless ``buffer_size``
        is given), so a loaded model predicts without allocating the training buffer. :meth:`learn` refills it from
        ``model.dataset`` when that names a dataset (or set ``model.replay_buffer`` by hand first)."""
        kwargs.setdefault("buffer_size", 1)
        kwargs["_fill_on_setup"] = False
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "actor_lr_schedule", "_fill_on_setup"]


#: SAC's keywords that an offline algorithm refuses, with why: ``(keyword, the value it accepts, the reason)``.
UNSUPPORTED_SAC_KEYWORDS = (
    ("use_sde", False, "gSDE explores by sampling noise matrices for rollouts; the conservative term and the warm start "
     "draw the policy's actions without it"),
    ("use_sde_at_warmup", False, "gSDE is not supported (use_sde)"),
    ("optimize_memory_usage", False, "the offline data keep each transition's next observation: an episode's last "
     "observation is not the next episode's first"),
)  # fmt: skip


def _refuse_unsupported(kwargs: dict[str, Any]) -> None:
    """One line for a SAC keyword set to a value an offline algorithm cannot honour."""
    for keyword, accepted, reason in UNSUPPORTED_SAC_KEYWORDS:
        if kwargs.get(keyword, accepted) != accepted:
            raise SettingError(f"{keyword}={kwargs[keyword]!r} is not supported: {reason}")
