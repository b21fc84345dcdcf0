"""The research tests' set-up: one torch thread a process (as the default suite's), and the default suite's helpers
(``tests/rollouts.py``) importable."""

import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
