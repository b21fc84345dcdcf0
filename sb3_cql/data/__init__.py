"""Behaviour datasets: collection into Minari datasets and bulk loading into SB3's ``ReplayBuffer``.

The collection (which imports the tasks and the simulator) loads on first use of one of its names, so that loading
a dataset, and the algorithms that do, import no simulator.
"""

from sb3_cql.data.ids import DEFAULT_NOISE, NAMESPACE, POLICIES, dataset_id, dataset_path
from sb3_cql.data.replay import DatasetError, check_spaces, fill_replay_buffer, load_dataset

#: Names of :mod:`sb3_cql.data.collection`, imported when first asked for.
_COLLECTION = ("CollectionSpec", "collect_dataset", "ensure_dataset", "mix_datasets", "standard_collection")


def __getattr__(name: str):
    if name in _COLLECTION:
        from sb3_cql.data import collection

        return getattr(collection, name)
    raise AttributeError(f"module 'sb3_cql.data' has no attribute {name!r}")


__all__ = [
    "DEFAULT_NOISE",
    "NAMESPACE",
    "POLICIES",
    "CollectionSpec",
    "DatasetError",
    "check_spaces",
    "collect_dataset",
    "dataset_id",
    "dataset_path",
    "ensure_dataset",
    "fill_replay_buffer",
    "load_dataset",
    "mix_datasets",
    "standard_collection",
]
