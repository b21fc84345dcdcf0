"""A config's ``chunked`` entry: settings that apply when the ``-i`` model acts in action chunks (``action_chunk`` > 1),
over the entry's own and below ``--hyperparams`` (``cql_finetune.yml``)."""

from __future__ import annotations

from typing import Any

from sb3_cql.zoo.errors import PROG
from sb3_cql.zoo.pretrained import saved_data

#: The config key.
CHUNKED_KEY = "chunked"


def apply_chunked_entry(manager: Any, hyperparams: dict[str, Any], saved_hyperparams: dict[str, Any]) -> None:
    """Add the ``chunked`` settings to both dicts for a chunked ``-i`` model; the key itself leaves them."""
    chunked = hyperparams.pop(CHUNKED_KEY, None)
    saved_hyperparams.pop(CHUNKED_KEY, None)
    if chunked is None:
        return
    if not isinstance(chunked, dict):
        raise SystemExit(f"{PROG}: error: {manager.config}: '{CHUNKED_KEY}' must be a mapping of settings, got {chunked!r}")
    if not manager.continue_training or saved_data(manager.trained_agent).get("action_chunk", 1) <= 1:
        return
    given = manager.custom_hyperparams or {}
    settings = {key: value for key, value in chunked.items() if key not in given}
    hyperparams.update(settings)
    saved_hyperparams.update(settings)
    print(f"{manager.trained_agent} acts in action chunks: the config's '{CHUNKED_KEY}' settings apply: {settings}")
