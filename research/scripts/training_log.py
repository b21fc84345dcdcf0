"""What a training printed, at chosen steps: how its losses and values moved, from the tables SB3 writes to stdout.

Usage: python research/scripts/training_log.py LOG [LOG ...] [--keys KEY ...] [--every STEPS]

``LOG`` is a training's saved stdout (``python -m rl_zoo3.train ... > runs/ROW-sS.train.log``, any algorithm at
``verbose`` 1), whose tables SB3's ``HumanOutputFormat`` prints at each dump of the logs (every 1,000 gradient steps
offline). For each log, one line per multiple of ``--every`` steps (``time/total_timesteps``): the table dumped
nearest that step, and in it each of ``--keys`` (SB3's names, such as ``train/critic_loss``). SB3 prints numbers
with 3 significant digits.

Printed (``--every 10000``)::

    runs/iql-yaw-ddpgawr4-40k-s1.train.log
      step 10000: train/iql_q_data 0.0243, train/iql_weight 1.11, train/critic_loss 0.00212
      step 20000: train/iql_q_data -0.44, train/iql_weight 3.53, train/critic_loss 0.736
      step 30000: train/iql_q_data -5.86, train/iql_weight 33.8, train/critic_loss 47.9
      step 40000: train/iql_q_data -22.2, train/iql_weight 50, train/critic_loss 590

A log without a table, or without one of the keys, is one line on stderr and exit status 1.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from _cli import positive_int

#: A row of SB3's stdout table: ``|    name    | value    |``, the name indented under its group (``| train/  |  |``).
ROW = re.compile(r"^\|(?P<indent> *)(?P<name>\S+) *\|(?P<value>[^|]*)\|\s*$")

DEFAULT_KEYS = ("train/iql_q_data", "train/iql_weight", "train/critic_loss")


def read_tables(text: str) -> list[dict[str, str]]:
    """Each table SB3 printed in ``text``, as ``{"group/name": value}``, in order."""
    tables: list[dict[str, str]] = []
    table: dict[str, str] = {}
    group = ""
    for line in text.splitlines():
        if line.startswith("---"):  # a table's top and bottom border
            if table:
                tables.append(table)
            table, group = {}, ""
            continue
        match = ROW.match(line)
        if match is None:
            continue
        name, value = match["name"], match["value"].strip()
        if len(match["indent"]) <= 1 and name.endswith("/") and not value:
            group = name
        else:
            table[group + name] = value
    if table:
        tables.append(table)
    return [table for table in tables if "time/total_timesteps" in table]


def at_steps(tables: list[dict[str, str]], every: int) -> list[tuple[int, dict[str, str]]]:
    """For each multiple of ``every`` up to the last step printed, the table printed nearest it (once each)."""
    steps = [int(table["time/total_timesteps"]) for table in tables]
    picked: list[tuple[int, dict[str, str]]] = []
    for target in range(every, steps[-1] + every, every):
        index = min(range(len(steps)), key=lambda i: abs(steps[i] - target))
        if not picked or picked[-1][0] != steps[index]:
            picked.append((steps[index], tables[index]))
    return picked


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/training_log.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("logs", nargs="+", type=Path, metavar="LOG", help="a training's saved stdout")
    parser.add_argument("--keys", nargs="+", default=list(DEFAULT_KEYS), help="SB3's names of the logged numbers")
    parser.add_argument("--every", type=positive_int, default=5000, help="steps between two lines (default 5000)")
    args = parser.parse_args(argv)
    for path in args.logs:
        try:
            text = path.read_text(errors="replace")
        except OSError as error:
            sys.exit(f"{path}: cannot read it ({error.strerror or error})")
        tables = read_tables(text)
        if not tables:
            sys.exit(f"{path}: no table of SB3's logs (time/total_timesteps) in it: is it a training's stdout at verbose 1?")
        missing = [key for key in args.keys if not any(key in table for table in tables)]
        if missing:
            names = sorted({key for table in tables for key in table})
            sys.exit(f"{path}: no {', '.join(missing)} in its tables; they have {', '.join(names)}")
        tables = [table for table in tables if any(key in table for key in args.keys)]  # not the evaluations' own
        print(path)
        for step, table in at_steps(tables, args.every):
            print(f"  step {step}: " + ", ".join(f"{key} {table.get(key, '-')}" for key in args.keys))


if __name__ == "__main__":
    main()
