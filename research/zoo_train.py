"""RL-Zoo3's training command with the research variants of ``research/iql_variants.py`` registered beside the
package's algorithms, as RL-Zoo3's ``train_sbx.py`` registers SBX's (a study's entry point, not installed with the
package), from the repository's root::

    python research/zoo_train.py --algo iql_capped --env PandaForce-v0 -i MODEL --conf-file CONFIG ...

Every option is the zoo's (``python -m rl_zoo3.train``); ``--algo`` also takes the names of :data:`VARIANTS`.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rl_zoo3 import utils  # noqa: E402
from rl_zoo3.train import train  # noqa: E402

from research.iql_variants import CappedIQL, OfflineAnchorIQL, SuccessAnchorIQL  # noqa: E402
from sb3_cql.common.atomic import with_atomic_saves  # noqa: E402
from sb3_cql.zoo.plugin import register  # noqa: E402

#: The zoo's names of the research variants.
VARIANTS = {"iql_capped": CappedIQL, "iql_offline_anchor": OfflineAnchorIQL, "iql_success_anchor": SuccessAnchorIQL}


def register_variants() -> None:
    """The package's algorithms and the research variants in RL-Zoo3's ``ALGOS``."""
    register()
    for name, algorithm in VARIANTS.items():
        utils.ALGOS[name] = with_atomic_saves(algorithm)


if __name__ == "__main__":
    register_variants()
    train()
