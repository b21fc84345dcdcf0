"""Count the episodes of a delta-action dataset whose gripper command opens again after it has closed.

Usage: python research/scripts/gripper_reopenings.py DATASET_ID

In delta mode the PD controllers command the gripper +1 (open) or -1 (close), the last action dimension. An episode
reopens when a +1 follows its first -1: the regrasping controllers (``pid-regrasp``, ``noisy-regrasp``) reopen to
grasp a lost object again, and with noise on the arm a closing can be aborted.

Prints one line and writes nothing::

    sb3cql/Panda-v0/noisy-regrasp-delta-v0: 10000 episodes, success rate 0.269, 5982 with a reopening (849 of them successful)

(an episode is successful when its rewards sum above 0). ``DATASET_ID`` is a Minari id under
``MINARI_DATASETS_PATH`` (default ``~/.minari/datasets``); a missing dataset is an error, not collected.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from sb3_cql.data import DatasetError, load_dataset


def reopens(gripper_commands: np.ndarray) -> bool:
    """Whether an episode's gripper commands (+1 open, -1 close, one per step) open again after the first close."""
    closed = np.flatnonzero(gripper_commands <= 0)
    return closed.size > 0 and bool((gripper_commands[closed[0] :] > 0).any())


def count(dataset) -> tuple[int, int, int, int]:
    """``(episodes, successful episodes, episodes with a reopening, successful episodes with a reopening)``."""
    episodes = successes = reopened = reopened_successes = 0
    for episode in dataset.iterate_episodes():
        reopening = reopens(episode.actions[:, -1])
        success = episode.rewards.sum() > 0
        episodes += 1
        successes += success
        reopened += reopening
        reopened_successes += reopening and success
    return episodes, successes, reopened, reopened_successes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/gripper_reopenings.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("dataset_id", metavar="DATASET_ID", help="Minari id of a delta-action dataset")
    args = parser.parse_args(argv)
    try:
        dataset = load_dataset(args.dataset_id)
    except DatasetError as error:
        sys.exit(f"error: {error}")
    episodes, successes, reopened, reopened_successes = count(dataset)
    print(
        f"{args.dataset_id}: {episodes} episodes, success rate {successes / episodes:.3f}, {reopened} with a reopening "
        f"({reopened_successes} of them successful)"
    )


if __name__ == "__main__":
    main()
