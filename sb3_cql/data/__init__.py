"""Behaviour datasets: collection into Minari datasets and bulk loading into SB3's ``ReplayBuffer``."""

from sb3_cql.data.collection import CollectionSpec, collect_dataset, ensure_dataset, mix_datasets, standard_collection
from sb3_cql.data.ids import DEFAULT_NOISE, NAMESPACE, POLICIES, dataset_id, dataset_path
from sb3_cql.data.replay import DatasetError, check_spaces, fill_replay_buffer, load_dataset

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
