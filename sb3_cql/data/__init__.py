"""Behaviour datasets: collection into Minari datasets and bulk loading into SB3's replay buffers.

One role a module, each importing only those below it:

- :mod:`~sb3_cql.data.errors`: :class:`DatasetError`, the package's error;
- :mod:`~sb3_cql.data.digest`: a dataset's arrays, or a buffer's transitions, as one SHA-256 (:func:`arrays_digest`,
  :func:`transitions_digest`);
- :mod:`~sb3_cql.data.ids`: dataset ids and paths, and the behaviour policies' names;
- :mod:`~sb3_cql.data.store`: a dataset on disk (its files and lock, recovery, publication) and its loading;
- :mod:`~sb3_cql.data.spaces`: whether a dataset or a model fits an env (:func:`check_spaces`);
- :mod:`~sb3_cql.data.replay`: Minari datasets into SB3's buffers by bulk copies;
- :mod:`~sb3_cql.data.selection`: episodes selected by their return;
- :mod:`~sb3_cql.data.rollouts`: what a dataset is made of, the behaviour policies, one episode;
- :mod:`~sb3_cql.data.estimates`, :mod:`~sb3_cql.data.assembly` and :mod:`~sb3_cql.data.collection`: a collection's
  time and disk, its assembly into a Minari dataset, and the collection itself (collect, ensure, mix, resume);
- :mod:`~sb3_cql.data.loading`: the one entry from an id, a Minari dataset or a buffer to a model's replay buffer
  (:func:`resolve_dataset`, :func:`fill_replay_buffer`, :func:`load_replay_buffer`), with the data checks.

The rollouts and the collection (which import the tasks and the simulator) load on first use of one of their names,
as do the policy names (read from the tasks), so that loading a dataset, and the algorithms that do, import no
simulator.
"""

from sb3_cql.data.digest import arrays_digest, transitions_digest
from sb3_cql.data.errors import DatasetError
from sb3_cql.data.ids import DEFAULT_NOISE, NAMESPACE, dataset_id, dataset_path
from sb3_cql.data.loading import fill_replay_buffer, load_replay_buffer, resolve_dataset
from sb3_cql.data.spaces import check_spaces
from sb3_cql.data.store import load_dataset

#: Names of :mod:`sb3_cql.data.collection`, imported when first asked for.
_COLLECTION = ("CollectionSpec", "collect_dataset", "ensure_dataset", "mix_datasets", "standard_collection")


def __getattr__(name: str):
    if name in _COLLECTION:
        from sb3_cql.data import collection

        return getattr(collection, name)
    if name == "POLICIES":
        from sb3_cql.data import ids

        return ids.POLICIES
    raise AttributeError(f"module 'sb3_cql.data' has no attribute {name!r}")


__all__ = [
    "DEFAULT_NOISE",
    "NAMESPACE",
    "POLICIES",
    "CollectionSpec",
    "DatasetError",
    "arrays_digest",
    "check_spaces",
    "collect_dataset",
    "dataset_id",
    "dataset_path",
    "ensure_dataset",
    "fill_replay_buffer",
    "load_dataset",
    "load_replay_buffer",
    "mix_datasets",
    "resolve_dataset",
    "standard_collection",
    "transitions_digest",
]
