"""Interpreter start-up with and without the zoo hook (``sb3_cql-zoo.pth``): the plugin must cost nothing measurable.

    python benchmarks/startup.py [--runs 40]

Runs ``python -c pass`` alternately with the installed ``.pth`` file and with it renamed away (it is always put
back), and prints the median and spread of each. Needs write access to site-packages.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

PTH = Path(sysconfig.get_paths()["purelib"]) / "sb3_cql-zoo.pth"


def start_up_seconds() -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "pass"], check=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=40)
    args = parser.parse_args()
    if not PTH.is_file():
        raise SystemExit(f"{PTH} is missing: install the package first (pip install -e .)")
    away = PTH.with_suffix(".pth.away")
    times: dict[str, list[float]] = {"with the hook": [], "without": []}
    try:
        for _ in range(args.runs):
            times["with the hook"].append(start_up_seconds())
            PTH.rename(away)
            try:
                times["without"].append(start_up_seconds())
            finally:
                away.rename(PTH)
    finally:
        if away.exists():
            away.rename(PTH)
    for name, values in times.items():
        print(f"{name:14s} median {statistics.median(values) * 1e3:5.1f} ms, quartiles "
              f"{statistics.quantiles(values)[0] * 1e3:5.1f}-{statistics.quantiles(values)[2] * 1e3:5.1f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
