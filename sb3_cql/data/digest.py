"""A dataset's arrays as one SHA-256 digest, stored in the metadata of each collection (``arrays_sha256``) so that two
datasets of the same id, collected on different machines, can be told apart or shown equal."""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from minari import MinariDataset

#: The fields of an episode the digest covers, in this order.
FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


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
