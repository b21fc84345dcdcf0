"""Minari datasets into SB3's replay buffers by bulk array assignment, with clear errors for bad data."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from minari import MinariDataset

from sb3_cql.data.errors import DatasetError
from sb3_cql.data.spaces import check_spaces, dataset_name

if TYPE_CHECKING:  # SB3 (and torch) load only when a buffer is filled: collection workers never need them.
    from stable_baselines3.common.buffers import ReplayBuffer

#: Episodes read at a time from a non-HDF5 dataset: the only copy of the data beside the buffer's arrays.
LOAD_BATCH_EPISODES = 256


def check_box_spaces(dataset: MinariDataset, observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """A :class:`DatasetError` unless the dataset's and the env's spaces are Box spaces (or Dict observations of them)."""
    pairs = (("observation", dataset.observation_space, observation_space), ("action", dataset.action_space, action_space))
    for what, data_space, env_space in pairs:
        if what == "observation" and isinstance(data_space, spaces.Dict) and isinstance(env_space, spaces.Dict):
            held = [*data_space.spaces.values(), *env_space.spaces.values()]
        else:
            held = [data_space, env_space]
        if not all(isinstance(space, spaces.Box) for space in held):
            raise DatasetError(
                f"dataset {dataset_name(dataset)}: only Box spaces (and Dict observations of them) are supported, got "
                f"{data_space} and {env_space}"
            )


def fill_from_minari(
    dataset: MinariDataset,
    observation_space: spaces.Box,
    action_space: spaces.Box,
    replay_buffer: ReplayBuffer | None = None,
    device: str = "auto",
    replay_buffer_class: type[ReplayBuffer] | None = None,
    replay_buffer_kwargs: dict[str, Any] | None = None,
    buffer_observation_space: spaces.Space | None = None,
) -> ReplayBuffer:
    """Append every transition of ``dataset`` to a ``ReplayBuffer`` and return the buffer: actions scaled to [-1, 1]
    as SB3's ``BasePolicy.scale_action``, ``dones`` the terminations and ``timeouts`` the truncations, one episode
    at a time copied by slices. The data must match the env's ``observation_space`` and ``action_space``.
    ``replay_buffer`` is appended to (a larger copy is returned where it is too small); ``None`` makes one of the
    dataset's size, of ``replay_buffer_class`` with ``replay_buffer_kwargs``, on ``device``, with
    ``buffer_observation_space`` where it is not the env's (images channel-first as SB3's ``VecTransposeImage`` gives
    them; data already channel-first load as they are)."""
    from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
    from stable_baselines3.common.vec_env import VecTransposeImage

    if buffer_observation_space is not None and _shapes(dataset.observation_space) == _shapes(buffer_observation_space):
        observation_space = buffer_observation_space  # images held as the policy sees them (channel-first): as they are
    check_box_spaces(dataset, observation_space, action_space)
    check_spaces(dataset, observation_space, action_space)
    name = dataset_name(dataset)
    # The storage's own count: MinariDataset.total_steps reads every episode's attributes.
    n_transitions = dataset.storage.total_steps if len(dataset) == dataset.storage.total_episodes else dataset.total_steps
    if n_transitions == 0:
        raise DatasetError(f"dataset {name} holds no transitions")
    buffer_space = observation_space if buffer_observation_space is None else buffer_observation_space
    if replay_buffer is None:
        buffer_class = replay_buffer_class or (DictReplayBuffer if isinstance(buffer_space, spaces.Dict) else ReplayBuffer)
        replay_buffer = buffer_class(n_transitions, buffer_space, action_space, device=device, **(replay_buffer_kwargs or {}))
    if replay_buffer.n_envs != 1 or replay_buffer.optimize_memory_usage:  # (a DictReplayBuffer has the same arrays)
        raise ValueError("a filled buffer needs a ReplayBuffer with n_envs=1 and optimize_memory_usage=False")
    if replay_buffer.full:
        raise ValueError("cannot append to a full buffer")
    start = replay_buffer.pos
    if start + n_transitions > replay_buffer.buffer_size:
        replay_buffer = _grown(replay_buffer, start + n_transitions)

    transposed = _transposed_keys(observation_space, replay_buffer.observation_space)
    actions = replay_buffer.actions[:, 0]
    scale = 2.0 / (action_space.high - action_space.low)
    position = start
    for episode_id, episode_observations, episode_actions, rewards, terminations, truncations in _episode_arrays(dataset):
        length = len(rewards)
        rows = slice(position, position + length)
        for key, array in _items(episode_observations):
            if key in transposed:  # channel-last images as SB3's VecTransposeImage gives them to the policy
                array = VecTransposeImage.transpose_image(array)
            _column(replay_buffer.observations, key)[rows] = array[:-1]
            _column(replay_buffer.next_observations, key)[rows] = array[1:]
        # 2 (a - low) / (high - low) - 1, in place: SB3's BasePolicy.scale_action.
        np.multiply(episode_actions - action_space.low, scale, out=actions[rows])
        actions[rows] -= 1.0
        replay_buffer.rewards[rows, 0] = rewards
        replay_buffer.dones[rows, 0] = terminations
        replay_buffer.timeouts[rows, 0] = truncations
        problem = _bad_values(episode_observations, episode_actions, rewards, action_space)
        if problem is not None:
            raise DatasetError(f"dataset {name}: episode {episode_id}, {problem}")
        position += length
    replay_buffer.pos = position % replay_buffer.buffer_size
    replay_buffer.full = position == replay_buffer.buffer_size
    return replay_buffer


#: How far a data action may lie outside the action space's bounds (float32 rounding of data written elsewhere).
BOUNDS_TOLERANCE = 1e-5


def _bad_values(
    observations: np.ndarray | dict[str, np.ndarray], actions: np.ndarray, rewards: np.ndarray, action_space: spaces.Box
) -> str | None:
    """Where an episode holds a NaN or infinite value, or an action outside ``action_space``, as ``"step T: ..."``."""
    checks = [(f"observation {key!r}" if key else "observation", array) for key, array in _items(observations)]
    for what, array in [*checks, ("action", actions), ("reward", rewards)]:
        flat = array.reshape(len(array), -1)
        bad = ~np.isfinite(flat)
        if bad.any():
            step, component = np.argwhere(bad)[0]
            where = f"[{component}]" if flat.shape[1] > 1 else ""
            return f"step {step}: {what}{where} is {flat[step, component]:g}, not finite"
    low, high = action_space.low.reshape(-1), action_space.high.reshape(-1)
    flat = actions.reshape(len(actions), -1)
    outside = (flat < low - BOUNDS_TOLERANCE * np.maximum(1.0, np.abs(low))) | (
        flat > high + BOUNDS_TOLERANCE * np.maximum(1.0, np.abs(high))
    )
    if outside.any():
        step, component = np.argwhere(outside)[0]
        return (
            f"step {step}: action[{component}] is {flat[step, component]:g}, outside the action space's bounds "
            f"[{low[component]:g}, {high[component]:g}] (data of another action mode?)"
        )
    return None


def _episode_arrays(
    dataset: MinariDataset,
) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """``(id, observations, actions, rewards, terminations, truncations)`` of each episode of ``dataset``: HDF5 ones
    through h5py's low-level calls (~290,000 transitions/s, Minari's reader ~74,000), others through Minari."""
    storage, indices = dataset.storage, dataset.episode_indices
    if storage.FORMAT != "hdf5" or isinstance(dataset.observation_space, spaces.Dict):  # Dicts are HDF5 groups
        for first in range(0, len(indices), LOAD_BATCH_EPISODES):
            for episode in dataset.iterate_episodes(indices[first : first + LOAD_BATCH_EPISODES]):
                yield episode.id, *(getattr(episode, field) for field in _FIELDS)
        return
    import h5py

    with h5py.File(storage.data_path / "main_data.hdf5", "r") as file:
        for index in indices:
            group = h5py.h5g.open(file.id, f"episode_{index}".encode())
            arrays = []
            for field in _FIELDS:
                data = h5py.h5d.open(group, field.encode())
                array = np.empty(data.get_space().shape, data.dtype)
                data.read(h5py.h5s.ALL, h5py.h5s.ALL, array)
                arrays.append(array)
            yield int(index), *arrays


_FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


def _items(observations: np.ndarray | dict[str, np.ndarray]) -> list[tuple[str | None, np.ndarray]]:
    """``(key, array)`` of Dict observations, ``(None, array)`` of Box ones."""
    return list(observations.items()) if isinstance(observations, dict) else [(None, observations)]


def _column(arrays: np.ndarray | dict[str, np.ndarray], key: str | None) -> np.ndarray:
    """A buffer's ``(buffer_size, 1, ...)`` array (of ``key`` for Dict observations) as ``(buffer_size, ...)``."""
    return (arrays if key is None else arrays[key])[:, 0]


def _transposed_keys(data_space: spaces.Space, buffer_space: spaces.Space) -> set[str | None]:
    """The observations (keys, ``None`` for a Box) channel-last in the data's space and channel-first in the buffer's."""
    data, buffer = dict(_space_items(data_space)), dict(_space_items(buffer_space))
    if set(data) != set(buffer):
        raise DatasetError(f"the buffer's observation space {buffer_space} does not hold the data's {data_space}")
    transposed = set()
    for key, space in data.items():
        shape, buffer_shape = space.shape, buffer[key].shape
        if shape != buffer_shape:
            if len(shape) != 3 or buffer_shape != (shape[2], shape[0], shape[1]):
                raise DatasetError(f"the buffer's observation shape {buffer_shape} does not hold the data's {shape}")
            transposed.add(key)
    return transposed


def _shapes(space: spaces.Space) -> dict[str | None, Any]:
    """The shape of a Box, or of each Box of a Dict, by key (``None`` for a Box)."""
    return {key: getattr(item, "shape", None) for key, item in _space_items(space)}


def _space_items(space: spaces.Space) -> list[tuple[str | None, spaces.Space]]:
    return list(space.spaces.items()) if isinstance(space, spaces.Dict) else [(None, space)]


def _grown(replay_buffer: ReplayBuffer, buffer_size: int) -> ReplayBuffer:
    """A copy of ``replay_buffer`` with room for ``buffer_size`` transitions."""
    from stable_baselines3.common.buffers import NStepReplayBuffer

    kwargs: dict[str, Any] = {"handle_timeout_termination": replay_buffer.handle_timeout_termination}
    if isinstance(replay_buffer, NStepReplayBuffer):
        kwargs.update(n_steps=replay_buffer.n_steps, gamma=replay_buffer.gamma)
    grown = type(replay_buffer)(
        buffer_size, replay_buffer.observation_space, replay_buffer.action_space, device=replay_buffer.device, **kwargs
    )
    size = replay_buffer.size()
    for field in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        old, new = getattr(replay_buffer, field), getattr(grown, field)
        for key, array in _items(old):
            (new if key is None else new[key])[:size] = array[:size]
    grown.pos = size
    return grown
