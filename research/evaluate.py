"""``python -m sb3_cql.evaluate`` with the research variants of :data:`research.zoo_train.VARIANTS` known to
``--algo`` (a study's entry point, not installed with the package), from the repository's root::

    python research/evaluate.py runs/ft-capped-s1/final.zip --algo iql_capped --env PandaForce-v0 Panda-v0 \\
        PandaPerturbed-v0 --seeds 50000-50099 --alignment --output final-eval.json

Every option is :mod:`sb3_cql.evaluate`'s.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from research.zoo_train import register_variants  # noqa: E402
from sb3_cql.evaluate import main  # noqa: E402
from sb3_cql.processes import run_command  # noqa: E402

if __name__ == "__main__":
    register_variants()
    run_command(main)
