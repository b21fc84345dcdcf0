"""Episodes of a Minari dataset selected by their return, through Minari's own ``filter_episodes``: the data of
filtered imitation (BC on the successful episodes, or on the best fraction of them)."""

from __future__ import annotations

import math
import numbers
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from minari import MinariDataset


def check_selection(min_return: float | None, top_fraction: float | None) -> str | None:
    """Why ``min_return`` and ``top_fraction`` cannot select episodes (a message naming the keyword), or ``None``."""
    if min_return is not None and not (_is_number(min_return) and math.isfinite(min_return)):
        return f"min_return must be a finite number or None, got {min_return!r}"
    if top_fraction is not None and not (_is_number(top_fraction) and 0 < top_fraction <= 1):
        return f"top_fraction must be in (0, 1] or None, got {top_fraction!r}"
    return None


def select_episodes(
    dataset: MinariDataset, min_return: float | None = None, top_fraction: float | None = None
) -> MinariDataset:
    """The episodes of ``dataset`` whose undiscounted return is at least ``min_return`` and, of those, the
    ``top_fraction`` with the highest returns (at least one; ties with the last one kept are kept too), as a view of
    the same files (``dataset.filter_episodes``); ``dataset`` itself for neither. ``ValueError`` for a setting out of
    range or a selection that keeps no episode."""
    problem = check_selection(min_return, top_fraction)
    if problem is not None:
        raise ValueError(problem)
    if min_return is None and top_fraction is None:
        return dataset
    returns = np.array([float(np.sum(episode.rewards)) for episode in dataset.iterate_episodes()])
    threshold = -np.inf if min_return is None else float(min_return)
    eligible = np.sort(returns[returns >= threshold])[::-1]
    if len(eligible) == 0:
        best = f"{returns.max():g}" if len(returns) else "none"
        raise ValueError(f"no episode of {dataset.spec.dataset_id} has a return >= {min_return:g} (it has "
                         f"{len(returns)} episodes, the highest return {best})")  # fmt: skip
    if top_fraction is not None:
        keep = max(1, math.ceil(top_fraction * len(eligible)))
        threshold = max(threshold, float(eligible[keep - 1]))
    return dataset.filter_episodes(lambda episode: float(np.sum(episode.rewards)) >= threshold)


def _is_number(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)
