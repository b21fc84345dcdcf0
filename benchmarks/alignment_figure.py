"""The alignment histograms of a set of evaluations: ``python -m sb3_cql.evaluate ... --alignment --output`` files.

    python benchmarks/alignment_figure.py results/offline-yaw/*.json --task PandaForce-v0 --output FIGURE.png

Files named ``ROW-seedN.json`` are one row, pooled over their seeds; any other file is a row of its own. The rows
are drawn in the order of the files given.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from sb3_cql.benchmark.plots import alignment_histograms


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("records", nargs="+", type=Path)
    parser.add_argument("--task", default="PandaForce-v0")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    rows: dict[str, list[dict]] = {}
    for path in args.records:
        rows.setdefault(re.sub(r"-seed\d+$", "", path.stem), []).append(json.loads(path.read_text()))
    alignment_histograms(rows, args.task, args.output)
    print(f"{args.output}: {len(rows)} rows ({', '.join(rows)})")


if __name__ == "__main__":
    main()
