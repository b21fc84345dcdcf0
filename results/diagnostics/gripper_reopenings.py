"""Count the episodes of a delta-action dataset whose gripper command opens again after it had closed.

Usage: python results/diagnostics/gripper_reopenings.py sb3cql/Panda-v0/x-rgnoisy-delta-v0

In delta mode the PD controllers command the gripper +1 (open) or -1 (close); a reopening is a change back to +1
after the first close.
"""

import sys

import numpy as np

from sb3_cql.data import load_dataset

dataset = load_dataset(sys.argv[1])
episodes = reopened = successes = reopened_successes = 0
for episode in dataset.iterate_episodes():
    opening = episode.actions[:, -1] > 0
    changes = np.flatnonzero(np.diff(opening.astype(int)))  # index before each change of command
    reopening = any(opening[change + 1] for change in changes[1:])
    success = episode.rewards.sum() > 0
    episodes += 1
    reopened += reopening
    successes += success
    reopened_successes += reopening and success
print(f"{sys.argv[1]}: {episodes} episodes, success rate {successes / episodes:.3f}, {reopened} with a reopening "
      f"({reopened_successes} of them successful)")  # fmt: skip
