"""The alignment histograms of a set of evaluations, from the files of ``python -m sb3_cql.evaluate ... --output``.

Usage: python research/scripts/alignment_figure.py RECORD.json [RECORD.json ...] --output FIGURE.png [--task TASK]

One panel a row: the share of the row's closings on a lying cylinder in each 10-degree bin of the angle between the
fingers' closing direction and the cylinder's axis (90: across it), on ``--task`` (PandaForce-v0), with the row's
mean success rate there. Files named ``ROW-seedN.json`` are one row, pooled over their seeds; any other file is a
row of its own. The rows are drawn in the order of the files given. Printed: the figure's path and its rows, then a
line a row: each task's mean success rate over the row's files (and each file's) and its failed episodes in which the
hand never closed (a policy that stops short of the grasp), and the share of ``--task``'s closings on a lying cylinder
at 60 degrees or more to its axis.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from sb3_cql.protocol.plots import alignment_histograms


def read_rows(paths: list[Path], task: str) -> dict[str, list[dict[str, Any]]]:
    """The records of ``paths`` grouped by row (the file name less ``-seedN``); one line of error for a file that
    is missing, not JSON, or has no episodes of ``task``."""
    rows: dict[str, list[dict[str, Any]]] = {}
    for path in paths:
        try:
            record = json.loads(path.read_text())
            record["tasks"][task]["episodes"]  # noqa: B018  (a record of this task)
        except (OSError, ValueError) as error:
            sys.exit(f"error: {path}: {error}")
        except (KeyError, TypeError):
            sys.exit(f"error: {path}: no evaluation of {task} (sb3_cql.evaluate --output with --env {task})")
        rows.setdefault(re.sub(r"-seed\d+$", "", path.stem), []).append(record)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/alignment_figure.py", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("records", nargs="+", type=Path, help="sb3_cql.evaluate --output files")
    parser.add_argument("--task", default="PandaForce-v0", help="the task whose closings are drawn (PandaForce-v0)")
    parser.add_argument("--output", type=Path, required=True, help="the figure (.png)")
    args = parser.parse_args(argv)
    rows = read_rows(args.records, args.task)
    alignment_histograms(rows, args.task, args.output)
    print(f"{args.output}: {len(rows)} rows ({', '.join(rows)})")
    for row, records in rows.items():
        print(f"{row}: {summary(records, args.task)}")


def summary(records: list[dict[str, Any]], task: str) -> str:
    """One line on a row's records: each task's success rate (the mean over the records, and each one's) and the
    failed episodes without a closing (summed over the records), and the share of ``task``'s closings on a lying
    cylinder at 60 degrees or more to its axis."""
    parts = []
    for name in records[0]["tasks"]:
        evaluations = [record["tasks"][name] for record in records if name in record["tasks"]]
        rates = [evaluation["success_rate"] for evaluation in evaluations]
        each = f" ({' '.join(f'{rate:.2f}' for rate in rates)})" if len(rates) > 1 else ""
        never_closed = sum(not episode["success"] and not episode["closing_angles"]
                           for evaluation in evaluations for episode in evaluation["episodes"])  # fmt: skip
        parts.append(f"{name} {sum(rates) / len(rates):.2f}{each}, {never_closed} failed without a closing")
    episodes = [episode for record in records for episode in record["tasks"][task]["episodes"]]
    angles = [angle for episode in episodes for angle in episode["closing_angles"] if angle is not None]
    across = sum(angle >= 60 for angle in angles) / len(angles) if angles else float("nan")
    return f"{', '.join(parts)}; {task}: {len(angles)} closings on a lying cylinder, {across:.2f} of them at 60-90 deg"


if __name__ == "__main__":
    main()
