"""Replay buffers of offline training and online fine-tuning: action chunks, returns-to-go (Cal-QL), and offline data
beside online transitions (RLPD)."""

from __future__ import annotations

import copy
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import NStepReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize


def with_n_step_returns(
    buffer: ReplayBuffer, n_steps: int, gamma: float, buffer_class: type[NStepReplayBuffer] = NStepReplayBuffer
) -> ReplayBuffer:
    """``buffer`` sampling SB3's ``n_steps``-step returns: for ``n_steps`` > 1, a plain ``ReplayBuffer``'s transitions
    (its arrays shared) in a ``buffer_class`` (``NStepReplayBuffer`` or :class:`ActionChunkReplayBuffer`); any other
    buffer as it is."""
    if n_steps <= 1 or type(buffer) is not ReplayBuffer:
        return buffer
    if buffer.optimize_memory_usage:
        raise ValueError("n-step returns do not support a buffer with optimize_memory_usage (SB3's NStepReplayBuffer)")
    n_step = buffer_class.__new__(buffer_class)
    n_step.__dict__.update(buffer.__dict__)
    n_step.n_steps, n_step.gamma = n_steps, gamma
    return n_step


class ActionChunkReplayBuffer(NStepReplayBuffer):
    """SB3's ``NStepReplayBuffer`` (of one env) whose samples' ``actions`` are the chunks of ``n_steps`` stored actions
    from each sampled step, ``(batch, n_steps * action_dim)``, for a critic of action chunks (Q-chunking); the rest are
    SB3's n-step samples over the same steps. It stores one transition a step; :meth:`single_step_samples` samples
    single actions.

    :param n_steps: actions per chunk, and steps of the n-step return.
    :param gamma: discount factor.
    """

    def __init__(self, *args: Any, n_steps: int = 5, gamma: float = 0.99, **kwargs: Any) -> None:
        super().__init__(*args, n_steps=n_steps, gamma=gamma, **kwargs)
        if self.n_envs != 1:
            raise ValueError(f"ActionChunkReplayBuffer holds the transitions of one env (n_envs=1), got n_envs={self.n_envs}")

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> ReplayBufferSamples:
        samples = super()._get_samples(batch_inds, env)
        return samples._replace(actions=self.to_torch(self.chunk_actions(batch_inds)))

    def chunk_actions(self, batch_inds: np.ndarray) -> np.ndarray:
        """The chunks of ``n_steps`` stored actions from rows ``batch_inds``, each cut at its episode's end where SB3's
        ``NStepReplayBuffer`` cuts the return (a termination, a truncation, the last row written), the last action
        repeated after it."""
        steps = np.arange(self.n_steps)
        rows = (batch_inds[:, None] + steps) % self.buffer_size
        # SB3's cut: a termination or truncation, or the last row written (an episode under way).
        ends = np.logical_or(self.dones[rows, 0], self.timeouts[rows, 0]) | (rows == (self.pos - 1) % self.buffer_size)
        last = np.where(ends.any(axis=1), ends.argmax(axis=1), self.n_steps - 1)
        rows = np.where(steps <= last[:, None], rows, rows[np.arange(len(rows)), last][:, None])
        return self.actions[rows, 0].reshape(len(batch_inds), -1)

    def single_step_samples(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        """SB3's ``ReplayBuffer`` sampling of the same transitions: one action each, one-step returns."""
        batch_inds = np.random.randint(0, self.buffer_size if self.full else self.pos, size=batch_size)
        return ReplayBuffer._get_samples(self, batch_inds, env)


def transposed_images(buffer: ReplayBuffer, observation_space: spaces.Space) -> ReplayBuffer:
    """A copy of ``buffer`` in ``observation_space``, its channel-last images channel-first as SB3's
    ``VecTransposeImage`` gives them to a policy."""
    from stable_baselines3.common.vec_env import VecTransposeImage

    kwargs: dict[str, Any] = {"handle_timeout_termination": buffer.handle_timeout_termination}
    if isinstance(buffer, NStepReplayBuffer):
        kwargs.update(n_steps=buffer.n_steps, gamma=buffer.gamma)
    copied = type(buffer)(buffer.buffer_size, observation_space, buffer.action_space, device=buffer.device,
                          n_envs=buffer.n_envs, **kwargs)  # fmt: skip
    for field in ("observations", "next_observations"):
        old, new = getattr(buffer, field), getattr(copied, field)
        for key in old if isinstance(old, dict) else [None]:
            source, target = (old, new) if key is None else (old[key], new[key])
            if source.shape == target.shape:
                target[:] = source
            else:  # (buffer_size, n_envs, H, W, C) -> (buffer_size, n_envs, C, H, W)
                target[:] = VecTransposeImage.transpose_image(source.reshape(-1, *source.shape[2:])).reshape(target.shape)
    for field in ("actions", "rewards", "dones", "timeouts"):
        getattr(copied, field)[:] = getattr(buffer, field)
    copied.pos, copied.full = buffer.pos, buffer.full
    return copied


class ReturnToGoSamples(NamedTuple):
    """SB3's ``ReplayBufferSamples`` and the return-to-go of each sampled state (``-inf`` where its episode has not
    ended yet)."""

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    returns_to_go: th.Tensor
    discounts: th.Tensor | None = None


def returns_to_go(rewards: np.ndarray, truncated: bool, gamma: float) -> np.ndarray:
    """Discounted returns-to-go ``G_t = r_t + gamma * G_{t+1}`` of one whole episode, in float64, ``G = 0`` after its
    last step. An episode ``truncated`` by a time limit whose ``rewards`` (as the critics see them) are all equal
    earns that reward forever, ``G_t = r / (1 - gamma)``, as the Cal-QL paper takes failed sparse-reward episodes."""
    rewards = np.asarray(rewards, dtype=np.float64)
    if truncated and len(rewards) > 0 and np.all(rewards == rewards[0]):
        return np.full(len(rewards), rewards[0] / (1.0 - gamma))
    result = np.empty(len(rewards))
    following = 0.0
    for step in range(len(rewards) - 1, -1, -1):
        following = rewards[step] + gamma * following
        result[step] = following
    return result


class ReturnToGoReplayBuffer(NStepReplayBuffer):
    """SB3's ``NStepReplayBuffer`` (of one env; ``n_steps`` 1 samples as ``ReplayBuffer``) with the discounted
    return-to-go (:func:`returns_to_go`) of every stored state under the critics' rewards ``reward_scale * reward +
    reward_bias``, sampled as :class:`ReturnToGoSamples`. Transitions added one at a time get theirs when their
    episode ends (``-inf`` until then); a buffer filled in bulk gets them from :meth:`compute_returns_to_go`.

    :param gamma: discount factor.
    :param n_steps: steps of SB3's n-step returns in the samples.
    :param reward_scale: the critics' reward scale.
    :param reward_bias: the critics' reward bias.
    """

    #: Buffers pickled before n-step samples were supported sample one-step returns.
    n_steps: int = 1

    def __init__(
        self,
        *args: Any,
        gamma: float = 0.99,
        n_steps: int = 1,
        reward_scale: float = 1.0,
        reward_bias: float = 0.0,
        **kwargs: Any,
    ) -> None:
        if kwargs.get("optimize_memory_usage"):
            raise ValueError("ReturnToGoReplayBuffer does not support optimize_memory_usage")
        super().__init__(*args, n_steps=n_steps, gamma=gamma, **kwargs)
        if self.n_envs != 1:
            raise ValueError(f"ReturnToGoReplayBuffer holds the transitions of one env (n_envs=1), got n_envs={self.n_envs}")
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        self.reward_scale, self.reward_bias = reward_scale, reward_bias
        self.returns_to_go = np.full((self.buffer_size, self.n_envs), -np.inf, dtype=np.float32)
        self.episode_starts = np.zeros(self.n_envs, dtype=np.int64)  # where each env's running episode began

    @classmethod
    def from_replay_buffer(
        cls, buffer: ReplayBuffer, gamma: float, reward_scale: float = 1.0, reward_bias: float = 0.0
    ) -> ReturnToGoReplayBuffer:
        """A buffer holding ``buffer``'s transitions (its arrays shared, its ``n_steps``) and their returns-to-go."""
        if buffer.optimize_memory_usage:
            raise ValueError("ReturnToGoReplayBuffer does not support optimize_memory_usage")
        if buffer.n_envs != 1:
            raise ValueError(f"ReturnToGoReplayBuffer holds the transitions of one env (n_envs=1), got n_envs={buffer.n_envs}")
        upgraded = cls.__new__(cls)
        upgraded.__dict__.update(buffer.__dict__)
        upgraded.n_steps = getattr(buffer, "n_steps", 1)
        upgraded.gamma, upgraded.reward_scale, upgraded.reward_bias = gamma, reward_scale, reward_bias
        upgraded.returns_to_go = np.full((buffer.buffer_size, buffer.n_envs), -np.inf, dtype=np.float32)
        upgraded.episode_starts = np.zeros(buffer.n_envs, dtype=np.int64)
        upgraded.compute_returns_to_go()
        return upgraded

    def compute_returns_to_go(self) -> None:
        """Returns-to-go of every ended episode in the buffer (``-inf`` for a trailing one without an end, which the
        next :meth:`add` continues)."""
        size = self.size()
        order = (np.arange(size) + (self.pos if self.full else 0)) % self.buffer_size
        for env in range(self.n_envs):
            start = 0
            ends = self.dones[order, env].astype(bool) | self.timeouts[order, env].astype(bool)
            for end in np.flatnonzero(ends):
                self._set_episode(order[start : end + 1], env)
                start = end + 1
            self.returns_to_go[order[start:], env] = -np.inf
            self.episode_starts[env] = order[start] if start < size else self.pos

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        row = self.pos
        super().add(obs, next_obs, action, reward, done, infos)
        self.returns_to_go[row] = -np.inf
        for env in np.flatnonzero(np.asarray(done).reshape(self.n_envs)):
            length = (row - self.episode_starts[env]) % self.buffer_size + 1
            rows = (self.episode_starts[env] + np.arange(length)) % self.buffer_size
            self._set_episode(rows, int(env))
            self.episode_starts[env] = self.pos

    def _set_episode(self, rows: np.ndarray, env: int) -> None:
        rewards = self.reward_scale * self.rewards[rows, env].astype(np.float64) + self.reward_bias
        truncated = bool(self.timeouts[rows[-1], env])
        self.returns_to_go[rows, env] = returns_to_go(rewards, truncated, self.gamma)

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> ReturnToGoSamples:
        # One-step samples are ReplayBuffer's own (SB3 uses NStepReplayBuffer for n_steps > 1 only).
        base = ReplayBuffer._get_samples(self, batch_inds, env) if self.n_steps == 1 else super()._get_samples(batch_inds, env)
        returns = self.to_torch(self.returns_to_go[batch_inds, 0].reshape(-1, 1))
        return ReturnToGoSamples(*base[:5], returns_to_go=returns, discounts=base.discounts)

    def start_new_episodes(self) -> None:
        """The next :meth:`add` starts a new episode (the env was reset): an unfinished one keeps ``-inf``."""
        self.episode_starts[:] = self.pos


#: What a :class:`MixedReplayBuffer` reads and writes as its online part's: SB3's ``ReplayBuffer`` attributes.
ONLINE_ATTRIBUTES = (
    "buffer_size", "observation_space", "action_space", "obs_shape", "action_dim", "n_envs", "pos", "full",
    "observations", "next_observations", "actions", "rewards", "dones", "timeouts", "optimize_memory_usage",
    "handle_timeout_termination",
)  # fmt: skip


class MixedReplayBuffer(ReplayBuffer):
    """Offline data and online transitions side by side, sampled as RLPD does (Ball et al. 2023,
    https://arxiv.org/abs/2302.02948): :meth:`add` stores in the ``online`` part, and every batch draws
    ``round(online_fraction * batch_size)`` samples from it (none while it is empty), the rest from ``offline``.

    Both parts are buffers of one class. As a ``ReplayBuffer`` it is the online part (its arrays, ``pos``, ``full``,
    ``buffer_size``), while :meth:`size` and :meth:`sample` count both. Pickled, it keeps the online transitions only
    (``offline`` is ``None`` until :meth:`set_offline`); ``copy.deepcopy`` copies both parts.

    :param offline: the offline data.
    :param online: the empty (or resumed) buffer of online transitions; its ``buffer_size`` is their capacity.
    :param online_fraction: the fraction of every batch drawn from the online transitions, in [0, 1].
    """

    def __init__(self, offline: ReplayBuffer | None, online: ReplayBuffer, online_fraction: float = 0.5) -> None:
        if not 0.0 <= online_fraction <= 1.0:
            raise ValueError(f"online_fraction must be in [0, 1], got {online_fraction}")
        # ReplayBuffer's __init__ would allocate arrays of its own: its attributes are the online part's instead.
        self.online, self.online_fraction, self.offline = online, online_fraction, None
        self.device = online.device
        if offline is not None:
            self.set_offline(offline)

    def set_offline(self, offline: ReplayBuffer) -> None:
        """Put the offline data in (after loading a pickled buffer, which holds the online transitions only)."""
        if type(offline) is not type(self.online):
            raise ValueError(f"the offline and online parts must be buffers of one class, got {type(offline).__name__} "
                             f"and {type(self.online).__name__}")  # fmt: skip
        if offline.obs_shape != self.online.obs_shape or offline.action_dim != self.online.action_dim:
            raise ValueError(
                f"the offline data's observations {offline.obs_shape} and actions ({offline.action_dim},) do not match "
                f"the online ones' {self.online.obs_shape} and ({self.online.action_dim},)"
            )
        offline.device = self.device
        self.offline = offline

    @property
    def device(self) -> th.device:
        return self._device

    @device.setter
    def device(self, device: th.device | str) -> None:  # SB3's load_replay_buffer moves a loaded buffer's device
        self._device = th.device(device) if isinstance(device, str) else device
        for part in (getattr(self, "offline", None), getattr(self, "online", None)):
            if part is not None:
                part.device = self._device

    def size(self) -> int:
        return self.online.size() + (0 if self.offline is None else self.offline.size())

    def add(self, *args: Any, **kwargs: Any) -> None:
        self.online.add(*args, **kwargs)

    def reset(self) -> None:
        """Forget the online transitions (the offline data stay)."""
        self.online.reset()

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples | ReturnToGoSamples:
        if self.offline is None:
            raise ValueError("the buffer has no offline data: set_offline() first (a pickled buffer leaves them out)")
        n_online = round(self.online_fraction * batch_size) if self.online.size() > 0 else 0
        parts = [part.sample(n, env) for part, n in ((self.offline, batch_size - n_online), (self.online, n_online)) if n]
        if len(parts) == 1:
            return parts[0]
        return type(parts[0])(*(_concatenated(fields) for fields in zip(*parts, strict=True)))

    def start_new_episodes(self) -> None:
        """See :meth:`ReturnToGoReplayBuffer.start_new_episodes` (nothing for a plain online part)."""
        if isinstance(self.online, ReturnToGoReplayBuffer):
            self.online.start_new_episodes()

    def __deepcopy__(self, memo: dict[int, Any]) -> MixedReplayBuffer:
        duplicate = type(self).__new__(type(self))
        memo[id(self)] = duplicate
        duplicate.__dict__.update(copy.deepcopy(self.__dict__, memo))  # both parts, unlike pickling
        return duplicate

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["offline"] = None
        online = self.online.__dict__.copy()  # the filled rows only: a checkpoint of 10,000 steps is not 1,000,000's
        size, capacity, trimmed = self.online.size(), self.online.buffer_size, []
        for key, value in online.items():
            arrays = value if isinstance(value, dict) else {None: value}  # Dict observations: one array a key
            if all(isinstance(array, np.ndarray) and array.ndim >= 2 and len(array) == capacity for array in arrays.values()):
                rows = {name: array[:size].copy() for name, array in arrays.items()}
                online[key], trimmed = (rows if isinstance(value, dict) else rows[None]), [*trimmed, key]
        state["online"] = (type(self.online), online, trimmed)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        online_class, online, trimmed = state["online"]
        for key in trimmed:  # back to the capacity, the rows past the filled ones as a new buffer's
            value = online[key]
            arrays = value if isinstance(value, dict) else {None: value}
            for name, array in arrays.items():
                shape = (online["buffer_size"], *array.shape[1:])
                # np.zeros leaves the untouched capacity unallocated (a million image rows would be gigabytes).
                full = np.full(shape, -np.inf, array.dtype) if key == "returns_to_go" else np.zeros(shape, array.dtype)
                full[: len(array)] = array
                arrays[name] = full
            online[key] = arrays if isinstance(value, dict) else arrays[None]
        state["online"] = online_class.__new__(online_class)
        state["online"].__dict__.update(online)
        self.__dict__.update(state)


def _concatenated(fields: tuple[Any, ...]) -> Any:
    """One field of several batches in one: tensors, Dict observations key by key, or ``None``."""
    if fields[0] is None:
        return None
    if isinstance(fields[0], dict):
        return {key: th.cat([field[key] for field in fields]) for key in fields[0]}
    return th.cat(fields)


def _online_attribute(name: str) -> property:
    return property(lambda self: getattr(self.online, name), lambda self, value: setattr(self.online, name, value))


for _name in ONLINE_ATTRIBUTES:
    setattr(MixedReplayBuffer, _name, _online_attribute(_name))
