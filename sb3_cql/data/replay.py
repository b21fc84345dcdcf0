"""Load Minari datasets into SB3's ``ReplayBuffer`` by bulk array assignment, with clear errors for bad data."""

from __future__ import annotations

import contextlib
import json
import shlex
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from minari import MinariDataset

from sb3_cql.data import ids

if TYPE_CHECKING:  # SB3 (and torch) load only when a buffer is filled: collection workers never need them.
    from stable_baselines3.common.buffers import ReplayBuffer

#: Episodes read at a time while filling a buffer from a non-HDF5 dataset (HDF5 ones are read one by one):
#: the only copy of the data beside the buffer's arrays.
LOAD_BATCH_EPISODES = 256


class DatasetError(ValueError):
    """A dataset that is missing, unreadable, or does not fit the environment."""


def load_dataset(dataset_id: str) -> MinariDataset:
    """Open the Minari dataset ``dataset_id``, with an error naming it (and how to make it) if it is missing,
    partial, damaged or unreadable. A replacement of it that a kill cut short is completed first
    (:meth:`~sb3_cql.data.partial.DatasetFiles.recover`), unless a collection of it is running."""
    from sb3_cql.data.partial import DatasetFiles

    files = DatasetFiles(dataset_id)
    if (files.publishing.exists() or files.old.exists()) and not files.is_locked():
        with contextlib.suppress(DatasetError, OSError), files.locked():
            files.recover()
    path = ids.dataset_path(dataset_id)
    if not ids.dataset_exists(dataset_id):
        if path.exists():
            raise DatasetError(damaged_dataset(dataset_id))
        partial = _partial_collection(files)
        if partial is not None:
            raise DatasetError(partial)
        raise DatasetError(
            f"dataset {dataset_id} not found at {path} (MINARI_DATASETS_PATH or ~/.minari/datasets); "
            f"collect it with: python -m sb3_cql.data collect --dataset-id {shlex.quote(dataset_id)} ..."
        )
    try:
        dataset = MinariDataset(path / "data")
        empty = dataset.total_episodes == 0
        if not empty:
            list(dataset.storage.get_episode_metadata([0, dataset.total_episodes - 1]))  # opens the data file
    except Exception as error:
        raise DatasetError(f"dataset {dataset_id} at {path} is truncated or corrupt: {error}") from error
    if empty:
        raise DatasetError(f"dataset {dataset_id} at {path} holds no episodes: nothing to train on; collect it again "
                           "(python -m sb3_cql.data collect ... --overwrite)")  # fmt: skip
    return dataset


def damaged_dataset(dataset_id: str) -> str:
    """What to say of a dataset folder without its ``data/metadata.json`` (Minari writes it last: without it, the
    folder cannot be read), and how to collect it again."""
    from sb3_cql.data.collection import standard_collection

    path = ids.dataset_path(dataset_id)
    spec = standard_collection(dataset_id)
    command = ids.collect_command(json.loads(spec.to_json()), dataset_id) if spec is not None else None
    again = command or f"python -m sb3_cql.data collect --dataset-id {shlex.quote(dataset_id)} ..."
    return (
        f"dataset {dataset_id} at {path} is damaged: it has no data/metadata.json and cannot be read; replace it with: "
        f"{again} --overwrite"
    )


def _partial_collection(files: Any) -> str | None:
    """What to say of an interrupted collection of ``files``'s dataset, or ``None`` if there is none."""
    from sb3_cql.data.partial import partial_summary

    summary = partial_summary(files)
    if summary is None:
        return None
    spec, collected = summary
    command = ids.collect_command(spec, files.dataset_id)
    resume = f"resume it with: {command}" if command else "the same collection (collect_dataset) resumes it"
    if files.storage_before_episode_files.is_dir():  # written before episode files: its metadata has a count
        with contextlib.suppress(OSError, ValueError, KeyError):
            metadata = json.loads((files.storage_before_episode_files / "metadata.json").read_text())
            collected += int(metadata["total_episodes"])
    return (
        f"dataset {files.dataset_id} is partial: its collection was interrupted after {collected} of "
        f"{spec['n_episodes']} episodes (kept in {files.partial}); {resume}"
    )


def _name(dataset: MinariDataset) -> str:
    """The dataset's id, or its folder for a dataset without one: the name every error gives."""
    return dataset.spec.dataset_id if dataset.spec else str(dataset.storage.data_path)


def check_spaces(dataset: MinariDataset, observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Raise :class:`DatasetError` unless the dataset's spaces have the env's shapes and bounds: Box spaces, or for
    observations a Dict of Box spaces with the env's keys."""
    name = _name(dataset)
    pairs = [("observation", dataset.observation_space, observation_space), ("action", dataset.action_space, action_space)]
    if isinstance(dataset.observation_space, spaces.Dict) and isinstance(observation_space, spaces.Dict):
        if set(dataset.observation_space.spaces) != set(observation_space.spaces):
            raise DatasetError(
                f"dataset {name}: observation keys {sorted(dataset.observation_space.spaces)} do not match the env's "
                f"{sorted(observation_space.spaces)}"
            )
        pairs[:1] = [(f"observation {key!r}", dataset.observation_space[key], observation_space[key])
                     for key in observation_space.spaces]  # fmt: skip
    for what, data_space, env_space in pairs:
        if not isinstance(data_space, spaces.Box) or not isinstance(env_space, spaces.Box):
            raise DatasetError(
                f"dataset {name}: only Box spaces (and Dict observations of them) are supported, got {data_space} and "
                f"{env_space}"
            )
        if data_space.shape != env_space.shape:
            raise DatasetError(f"dataset {name}: {what} shape {data_space.shape} does not match the env's {env_space.shape}")
        if not (np.allclose(data_space.low, env_space.low) and np.allclose(data_space.high, env_space.high)):
            raise DatasetError(
                f"dataset {name}: {what} bounds do not match the env's (another action mode or task?): "
                f"dataset {data_space}, env {env_space}"
            )


def fill_replay_buffer(
    dataset: MinariDataset | str,
    observation_space: spaces.Box,
    action_space: spaces.Box,
    replay_buffer: ReplayBuffer | None = None,
    device: str = "auto",
    replay_buffer_class: type[ReplayBuffer] | None = None,
    replay_buffer_kwargs: dict[str, Any] | None = None,
    buffer_observation_space: spaces.Space | None = None,
) -> ReplayBuffer:
    """Append every transition of ``dataset`` to a ``ReplayBuffer`` and return the buffer.

    ``observations`` are each episode's observations but the last, ``next_observations`` all but the first,
    actions are scaled to [-1, 1] as SB3's policies scale them (``BasePolicy.scale_action``), ``dones`` are
    the terminations and ``timeouts`` the truncations (SB3 bootstraps through a timeout). Whole episodes are
    copied into the arrays by slices, so the only copy of the data beside the buffer is one episode (one batch
    for non-HDF5 datasets).

    :param dataset: a Minari dataset or its id.
    :param observation_space: the env's observation space (the dataset must match it).
    :param action_space: the env's action space (the dataset must match it).
    :param replay_buffer: a buffer to append to; if it cannot hold its content and the dataset, a larger one
        holding both is returned instead. ``None`` makes one of exactly the dataset's size.
    :param device: the device of a buffer made here.
    :param replay_buffer_class: the class of a buffer made here (SB3's ``ReplayBuffer`` by default; its
        ``NStepReplayBuffer`` samples n-step returns within each episode).
    :param replay_buffer_kwargs: keywords of a buffer made here (``n_steps`` and ``gamma`` of an
        ``NStepReplayBuffer``).
    :param buffer_observation_space: the observation space of a buffer made here where it is not the env's: SB3's
        ``VecTransposeImage`` makes channel-last images channel-first for the policy, and the data's images are
        transposed as it transposes them; data whose images are already channel-first (the buffer's shapes) load as
        they are. Dict observations load into a ``DictReplayBuffer``.
    """
    from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
    from stable_baselines3.common.vec_env import VecTransposeImage

    if isinstance(dataset, str):
        dataset = load_dataset(dataset)
    if buffer_observation_space is not None and _shapes(dataset.observation_space) == _shapes(buffer_observation_space):
        observation_space = buffer_observation_space  # images held as the policy sees them (channel-first): as they are
    check_spaces(dataset, observation_space, action_space)
    name = _name(dataset)
    # The storage's own count: MinariDataset.total_steps reads every episode's attributes.
    n_transitions = dataset.storage.total_steps if len(dataset) == dataset.storage.total_episodes else dataset.total_steps
    if n_transitions == 0:
        raise DatasetError(f"dataset {name} holds no transitions")
    buffer_space = observation_space if buffer_observation_space is None else buffer_observation_space
    if replay_buffer is None:
        buffer_class = replay_buffer_class or (DictReplayBuffer if isinstance(buffer_space, spaces.Dict) else ReplayBuffer)
        replay_buffer = buffer_class(n_transitions, buffer_space, action_space, device=device, **(replay_buffer_kwargs or {}))
    if replay_buffer.n_envs != 1 or replay_buffer.optimize_memory_usage:  # (a DictReplayBuffer has the same arrays)
        raise ValueError("fill_replay_buffer needs a ReplayBuffer with n_envs=1 and optimize_memory_usage=False")
    if replay_buffer.full:
        raise ValueError("fill_replay_buffer cannot append to a full buffer")
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
    """Where an episode holds a NaN or infinite value, or an action outside ``action_space`` (data of another action
    mode), as ``"step T: ..."``; ``None`` if nowhere."""
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
    """``(id, observations, actions, rewards, terminations, truncations)`` of each episode of ``dataset``.

    HDF5 datasets are read with h5py's low-level calls, one episode group after the other: Minari's own
    reader (which also decodes infos and builds an ``EpisodeData``) loads ~74,000 transitions/s here, these
    calls ~290,000. Other formats go through Minari, ``LOAD_BATCH_EPISODES`` episodes at a time.
    """
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
    """The observations (keys of Dict ones, ``None`` for a Box) that SB3's ``VecTransposeImage`` transposed: channel-last
    in the data's space, channel-first in the buffer's."""
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
