"""The one entry from a dataset to a model's replay buffer: :func:`resolve_dataset` turns an id, a Minari dataset or a
filled SB3 buffer into data (a missing standard id is collected first, and only then are the collection and the tasks
imported), and :func:`load_replay_buffer` gives the buffer an algorithm trains on, with the data checks: the spaces, a
NaN or an infinity, actions outside [-1, 1] in a buffer of the user's, no transitions at all."""

from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces
from minari import MinariDataset

from sb3_cql.data import ids
from sb3_cql.data.errors import DatasetError
from sb3_cql.data.replay import fill_from_minari
from sb3_cql.data.store import load_dataset

if TYPE_CHECKING:  # SB3 (and torch) load only when a buffer is filled: collection workers never need them.
    from stable_baselines3.common.buffers import ReplayBuffer

#: How far a buffer's scaled action may lie outside [-1, 1] (float32 rounding of data scaled elsewhere).
SCALED_ACTION_TOLERANCE = 1e-5


def resolve_dataset(dataset: Any) -> MinariDataset | ReplayBuffer:
    """The data ``dataset`` names: a Minari dataset or an SB3 ``ReplayBuffer`` as they are, an id loaded (a missing
    standard id, ``sb3cql/<task>/<policy>...-v0``, collected first by :func:`~sb3_cql.data.ensure_dataset`).

    :raises DatasetError: the id is missing and not a standard one, or ``dataset`` is none of the three.
    """
    from stable_baselines3.common.buffers import ReplayBuffer

    if isinstance(dataset, (MinariDataset, ReplayBuffer)):
        return dataset
    if not isinstance(dataset, str):
        raise DatasetError(f"dataset must be a Minari dataset, its id or a filled SB3 ReplayBuffer, got "
                           f"{type(dataset).__name__}")  # fmt: skip
    if ids.dataset_exists(dataset):
        data = load_dataset(dataset)
    else:
        from sb3_cql.data.collection import ensure_dataset  # the tasks load only to collect a standard dataset

        data = ensure_dataset(dataset)
    check_standard_data(dataset, data)
    return data


def check_standard_data(dataset_id: str, data: MinariDataset) -> None:
    """The data under a standard id are its collection's (:func:`~sb3_cql.data.ids.standard_mismatch`), else (a mix or
    data written by hand too) one :class:`DatasetError`; its first episodes only are one line on stderr."""
    standard = ids.standard_collection_fields(dataset_id) if dataset_id.startswith(f"{ids.NAMESPACE}/") else None
    if standard is None:  # (whether an id is a standard one is read from the tasks: only for this namespace's ids)
        return
    where = f"the dataset at {ids.dataset_path(dataset_id)}"
    try:
        fields = json.loads(data.storage.metadata["collection"])
    except (KeyError, TypeError, ValueError):
        fields = None
    if isinstance(fields, dict):
        mismatch = ids.standard_mismatch(dataset_id, fields, where)
    else:
        mismatch = f"{dataset_id} is a standard dataset id and {where} records no collection (a mix, or data written by hand)"
    complete = ids.collect_command(standard, dataset_id)
    if mismatch is not None:
        raise DatasetError(f"{mismatch}: move it to an id of its own (python -m sb3_cql.data info {dataset_id} shows what "
                           f"it holds), then {complete} collects {dataset_id}")  # fmt: skip
    if data.total_episodes < standard["n_episodes"]:
        print(f"{dataset_id} holds {data.total_episodes} of the {standard['n_episodes']} episodes its id defines (their "
              f"first ones): using these; {complete} --overwrite collects them all", file=sys.stderr, flush=True)  # fmt: skip


def fill_replay_buffer(
    dataset: MinariDataset | str,
    observation_space: spaces.Space,
    action_space: spaces.Box,
    replay_buffer: ReplayBuffer | None = None,
    device: str = "auto",
    replay_buffer_class: type[ReplayBuffer] | None = None,
    replay_buffer_kwargs: dict[str, Any] | None = None,
    buffer_observation_space: spaces.Space | None = None,
) -> ReplayBuffer:
    """Append every transition of ``dataset`` (a Minari dataset or its id, :func:`resolve_dataset`) to a
    ``ReplayBuffer`` and return the buffer (:func:`~sb3_cql.data.replay.fill_from_minari`, whose parameters these are)."""
    data = resolve_dataset(dataset)
    if not isinstance(data, MinariDataset):
        raise DatasetError(f"fill_replay_buffer reads a Minari dataset or its id, got {type(data).__name__}")
    return fill_from_minari(data, observation_space, action_space, replay_buffer, device, replay_buffer_class,
                            replay_buffer_kwargs, buffer_observation_space)  # fmt: skip


def load_replay_buffer(
    dataset: Any,
    observation_space: spaces.Space,
    action_space: spaces.Box,
    data_observation_space: spaces.Space | None = None,
    device: str = "auto",
    replay_buffer_class: type[ReplayBuffer] | None = None,
    replay_buffer_kwargs: dict[str, Any] | None = None,
) -> ReplayBuffer:
    """The replay buffer a model trains on from ``dataset`` (what :func:`resolve_dataset` takes): a buffer of the
    user's checked and returned as it is, a Minari dataset loaded into a new buffer of ``replay_buffer_class`` (with
    ``replay_buffer_kwargs``, on ``device``). ``observation_space`` is the model's (channel-first images after SB3's
    ``VecTransposeImage``), ``data_observation_space`` the env's as the data hold it, where it is not that one.

    :raises DatasetError: the data do not fit the spaces, hold a non-finite value or an action outside [-1, 1], or no
        transition.
    """
    from stable_baselines3.common.buffers import ReplayBuffer
    from stable_baselines3.common.preprocessing import get_obs_shape

    data_space = observation_space if data_observation_space is None else data_observation_space
    data = resolve_dataset(dataset)
    if isinstance(data, ReplayBuffer):
        fits = data.obs_shape in (get_obs_shape(observation_space), get_obs_shape(data_space))
        if not fits or data.action_dim != action_space.shape[0]:
            raise DatasetError(
                f"dataset: the replay buffer's observations {data.obs_shape} and actions ({data.action_dim},) "
                f"do not match the env's {get_obs_shape(data_space)} and {action_space.shape}"
            )
        check_buffer_values(data)
        return data
    return fill_from_minari(data, data_space, action_space, device=device, replay_buffer_class=replay_buffer_class,
                            replay_buffer_kwargs=replay_buffer_kwargs, buffer_observation_space=observation_space)  # fmt: skip


def check_buffer_values(buffer: ReplayBuffer) -> None:
    """:class:`DatasetError` for a buffer of the user's that holds no transition, a NaN or an infinity
    (:func:`first_non_finite`), or an action outside [-1, 1] (:func:`first_action_outside`)."""
    if buffer.size() == 0:
        raise DatasetError("dataset: the replay buffer holds no transitions")
    non_finite = first_non_finite(buffer)
    if non_finite is not None:  # it would train on as a NaN loss, or a distribution torch refuses
        field, index, env, value = non_finite
        at = f"index {index}" + (f", env {env}" if buffer.n_envs > 1 else "")
        raise DatasetError(f"dataset: the replay buffer's {field} hold {value} at {at}: every value must be finite")
    outside = first_action_outside(buffer)
    if outside is not None:  # SB3 stores actions scaled to the policy's [-1, 1]; a tanh policy never reaches them
        index, env, component, value = outside
        at = f"index {index}" + (f", env {env}" if buffer.n_envs > 1 else "")
        raise DatasetError(f"dataset: the replay buffer's actions hold {value:g} at {at} (action[{component}]), outside "
                           "[-1, 1]: store actions scaled as SB3 does (policy.scale_action)")  # fmt: skip


def first_non_finite(buffer: ReplayBuffer) -> tuple[str, int, int, float] | None:
    """The first NaN or infinity among the filled transitions of ``buffer``: ``(field, index, env, value)`` (field
    ``observations['key']`` for a dict of them); ``None`` if all are finite."""
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


def first_action_outside(buffer: ReplayBuffer) -> tuple[int, int, int, float] | None:
    """The first action among the filled transitions of ``buffer`` outside [-1, 1] (SB3's buffers hold scaled ones):
    ``(index, env, component, value)``; ``None`` if all lie inside (NaN too: :func:`first_non_finite` finds it)."""
    size = buffer.size()
    filled = buffer.actions[:size].reshape(size, buffer.n_envs, -1)
    bad = np.argwhere(np.abs(filled) > 1.0 + SCALED_ACTION_TOLERANCE)
    if not len(bad):
        return None
    index, env, component = bad[0]
    return int(index), int(env), int(component), float(filled[index, env, component])
