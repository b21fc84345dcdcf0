"""What fine-tuning runs did, from their zoo folders: evaluations against env steps (a figure, mean and 95% CI over the
runs), and per block of env steps the online episodes' successes and how their fingers closed on a fallen cylinder.

Usage: python research/scripts/finetune_record.py RUN [RUN ...] --output FIGURE.png [--block 20000] [--labels NAME ...]

Each RUN is a zoo run folder of a fine-tuning (``logs/cql/PandaForce-v0_1``): its ``evaluations.npz`` (the zoo's
evaluations during training), ``0.monitor.csv`` (each online episode's length and success) and the checkpoint's
replay buffer with the most steps (``rl_model_replay_buffer_<N>_steps.pkl``: the online transitions). Printed, a run
at a time: the evaluations' success rates; then for each ``--block`` of env steps, the online episodes that ended in
it and their successes, and of those whose fingers closed on a cylinder lying on its side, how many closed within 20
degrees of across its axis at least once (:func:`envs.pd_controller.closing_angles` of 70 degrees or more; for
the episodes that ended by the checkpoint, and only for the blocks its buffer reaches), and how many of those
succeeded. The
figure draws the evaluations of every run (labelled by ``--labels``, else by its folder) and their mean, with a
Student-t 95% interval from three runs on.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from _cli import positive_int  # noqa: E402
from stable_baselines3.common.save_util import load_from_pkl  # noqa: E402

from envs.pd_controller import closing_angles  # noqa: E402
from sb3_cql.common import MixedReplayBuffer  # noqa: E402
from sb3_cql.protocol.plots import mean_ci95  # noqa: E402

#: A closing at this angle or more (degrees between the closing direction and a lying cylinder's axis) is within 20
#: degrees of across the axis.
TURNED = 70.0


def latest_buffer(run: Path) -> Path | None:
    """The checkpoint replay buffer of ``run`` with the most steps, if any."""
    found = [(int(match.group(1)), path) for path in run.glob("rl_model_replay_buffer_*_steps.pkl")
             if (match := re.fullmatch(r"rl_model_replay_buffer_(\d+)_steps\.pkl", path.name))]  # fmt: skip
    return max(found)[1] if found else None


def online_closings(buffer_path: Path) -> tuple[int, list[tuple[int, list[float], bool]]]:
    """The transitions in a fine-tuning checkpoint's buffer and, for each ended online episode in it, in order,
    ``(env steps at its end, closing angles on a lying cylinder, whether it succeeded)`` (a success ends the episode:
    a termination, not the time limit)."""
    buffer = load_from_pkl(buffer_path)
    online = buffer.online if isinstance(buffer, MixedReplayBuffer) else buffer
    size = online.size()
    ends = np.flatnonzero((online.dones[:size, 0] > 0) | (online.timeouts[:size, 0] > 0))
    episodes, start = [], 0
    for end in ends:
        observations = np.concatenate([online.observations[start : end + 1, 0], online.next_observations[end : end + 1, 0]])
        angles = [angle for angle in closing_angles(observations) if angle is not None]
        episodes.append((int(end) + 1, angles, not online.timeouts[end, 0]))
        start = end + 1
    return size, episodes


def read_run(run: Path) -> dict[str, Any]:
    """A run's evaluations, online episodes (end step, success) and online closings; one line of error where a file
    is missing."""
    try:
        evaluations = np.load(run / "evaluations.npz")
        monitor = pd.read_csv(run / "0.monitor.csv", skiprows=1)
    except (OSError, ValueError) as error:
        sys.exit(f"error: {run}: {error}")
    buffer = latest_buffer(run)
    covered, closings = (0, []) if buffer is None else online_closings(buffer)
    return {
        "steps": evaluations["timesteps"],
        "success": evaluations["successes"].mean(axis=1),
        "episodes": list(zip(monitor["l"].cumsum().tolist(), monitor["is_success"].astype(bool).tolist(), strict=True)),
        "closings": closings,
        "covered": covered,
    }


def block_lines(record: dict[str, Any], block: int) -> list[str]:
    """One line per ``block`` env steps: the online episodes that ended in it, their successes, and their closings."""
    last = max([end for end, _ in record["episodes"]] or [0])
    lines = []
    for low in range(0, last, block):
        high = low + block
        ended = [success for end, success in record["episodes"] if low < end <= high]
        closed = [(angles, success) for end, angles, success in record["closings"] if low < end <= high and angles]
        turned = [success for angles, success in closed if max(angles) >= TURNED]
        line = f"  {low:,}-{high:,} env steps: {sum(ended)} of {len(ended)} online episodes succeeded"
        if low < record["covered"]:  # the checkpoint's buffer holds (some of) the block
            line += (f"; closings on a lying cylinder in {len(closed)}, {len(turned)} within 20 deg of across it "
                     f"({sum(turned)} of them succeeded)")  # fmt: skip
        lines.append(line)
    return lines


def figure(records: dict[str, dict[str, Any]], path: Path) -> None:
    """The evaluations of every run against env steps, and their mean with a 95% interval on the common steps."""
    fig, axis = plt.subplots(figsize=(7, 4))
    for name, record in records.items():
        axis.plot(record["steps"], record["success"], lw=0.8, alpha=0.5, label=name)
    common = min(len(record["steps"]) for record in records.values())
    steps = next(iter(records.values()))["steps"][:common]
    curves = np.array([record["success"][:common] for record in records.values()])
    mean, half = mean_ci95(curves)
    axis.plot(steps, mean, color="black", lw=2, label=f"mean of {len(records)}")
    if len(records) >= 3:  # with two, Student's t makes the interval wider than the axis
        axis.fill_between(steps, np.clip(mean - half, 0, 1), np.clip(mean + half, 0, 1), color="black", alpha=0.15)
    axis.set(xlabel="env steps", ylabel="evaluation success rate", ylim=(-0.02, 1.02))
    axis.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/finetune_record.py", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("runs", nargs="+", type=Path, help="zoo run folders of fine-tunings")
    parser.add_argument("--output", type=Path, required=True, help="the figure (.png)")
    parser.add_argument("--block", type=positive_int, default=20_000, help="env steps per block of online episodes")
    parser.add_argument("--labels", nargs="+", help="the runs' names in the figure and the output (one a run)")
    args = parser.parse_args(argv)
    if args.labels is not None and len(args.labels) != len(args.runs):
        parser.error(f"--labels: {len(args.labels)} names for {len(args.runs)} runs")
    records = {name: read_run(run) for name, run in zip(args.labels or map(str, args.runs), args.runs, strict=True)}
    figure(records, args.output)
    print(f"{args.output}: evaluations of {len(records)} runs")
    for name, record in records.items():
        rates = " ".join(f"{rate:.2f}" for rate in record["success"])
        print(f"{name}: evaluations at {', '.join(f'{step:,}' for step in record['steps'])} env steps: {rates}")
        for line in block_lines(record, args.block):
            print(line)


if __name__ == "__main__":
    main()
