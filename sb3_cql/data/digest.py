"""A dataset's arrays as one SHA-256 digest, stored in the metadata of each collection (``arrays_sha256``) so that two
datasets of the same id, collected on different machines, can be told apart or shown equal; and the transitions a
replay buffer holds as one, which a model keeps of the data it was trained on (``data_sha256``)."""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from minari import MinariDataset
    from stable_baselines3.common.buffers import ReplayBuffer

#: The fields of an episode the digest covers, in this order.
FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")
#: The fields of a replay buffer's transitions :func:`transitions_digest` covers, in this order.
BUFFER_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def update_digest(digest: Any, episode: Any) -> None:
    """Add one episode's arrays (:data:`FIELDS`, each with its dtype and shape) to ``digest``, a ``hashlib`` hash.
    ``episode`` is a Minari ``EpisodeBuffer`` or ``EpisodeData``: both give the same bytes."""
    for field in FIELDS:
        array = np.ascontiguousarray(getattr(episode, field))
        digest.update(f"{field}:{array.dtype.str}:{array.shape};".encode())
        digest.update(array.tobytes())


def arrays_digest(dataset: MinariDataset) -> str:
    """The SHA-256 of ``dataset``'s arrays, episode by episode in order: equal for two datasets exactly when their
    observations, actions, rewards, terminations and truncations are, whatever their ids or metadata. A collection
    stores it as ``dataset.storage.metadata["arrays_sha256"]``."""
    digest = hashlib.sha256()
    for episode in dataset.iterate_episodes():
        update_digest(digest, episode)
    return digest.hexdigest()


def transitions_digest(buffer: ReplayBuffer) -> str:
    """The SHA-256 of the transitions ``buffer`` holds (its first ``size()`` rows of :data:`BUFFER_FIELDS`, Dict
    observations key by key): equal for two buffers exactly when they hold the same transitions in the same order,
    whatever their class. A model records it of the offline data it was trained on, and compares it when it loads
    them again (:class:`~sb3_cql.common.OfflineSAC`)."""
    digest = hashlib.sha256()
    size = buffer.size()
    for field in BUFFER_FIELDS:
        value = getattr(buffer, field)
        if value is None:  # next_observations of a buffer that optimizes memory
            continue
        for key, array in sorted(value.items()) if isinstance(value, dict) else [("", value)]:
            rows = np.ascontiguousarray(array[:size])
            digest.update(f"{field}{'.' + key if key else ''}:{rows.dtype.str}:{rows.shape};".encode())
            digest.update(rows.tobytes())
    return digest.hexdigest()
