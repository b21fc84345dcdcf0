"""What a collection will take (about how long and how much disk), printed before it starts, and the disk check."""

from __future__ import annotations

import os
import shutil
from typing import TYPE_CHECKING

import envs
from sb3_cql.data.errors import DatasetError
from sb3_cql.data.ids import POLICIES, RANDOM_POLICY

if TYPE_CHECKING:
    from sb3_cql.data.rollouts import CollectionSpec
    from sb3_cql.data.store import DatasetFiles

# Measured on this project's 2-core machine; other jobs on the CPUs slow a collection (to 30-75% on 2026-12-01).

#: Mean transitions of an episode by task and policy: the PD controllers finish most Panda-v0 episodes in ~178 steps,
#: the noisy ones run most of them to the 700-step limit. Means over ``python -m sb3_cql.data collect --env ENV
#: --policy POLICY --episodes N`` (2026-12-01) with N = 100 to 200 for Panda-v0's noisy policies and PD controller,
#: 15 to 60 for the others; the action mode changes them by ~3% (Panda-v0's noisy-regrasp: 585 delta, 570 absolute).
#: The random-yaw policies' are the means over both action modes of the first 10 episodes from seed 0 (``collect_dataset``
#: with ``n_episodes=10``, 2026-12-02): a handful, so rougher (the modes' means differ by 1 to 4%).
EPISODE_STEPS = {
    "Panda-v0": {"pid": 178, "pid-regrasp": 178, "noisy": 629, "noisy-regrasp": 580, "pid-regrasp-yaw": 182,
                 "noisy-regrasp-yaw": 614, "random": 700},
    "PandaForce-v0": {"pid": 700, "pid-regrasp": 674, "noisy": 652, "noisy-regrasp": 700, "pid-regrasp-yaw": 696,
                      "noisy-regrasp-yaw": 678, "random": 700},
    "PandaPerturbed-v0": {"pid": 258, "pid-regrasp": 258, "noisy": 680, "noisy-regrasp": 642, "pid-regrasp-yaw": 184,
                          "noisy-regrasp-yaw": 676, "random": 700},
}  # fmt: skip
#: Transitions/s of one worker running a PD controller (noisy or not): 1,255 in ``python benchmarks/collect_speed.py``
#: (2026-11-22; 2,598 with 2 workers). Uniform random actions skip the controller's inverse kinematics: 1.8 to 2.2
#: times faster in back-to-back collections (2026-12-01). A model policy's speed is not estimated.
TRANSITIONS_PER_S = {"controller": 1_250, "random": 2_500}
#: Seconds before a worker's first episode (interpreter, imports, env and controller): 1.7 to 2.1 s in ``python -c
#: "from sb3_cql.data import collection as c; c._init_worker(c.CollectionSpec())"`` (2026-12-01, on a busy machine).
WORKER_START_S = 2.0
#: Disk of a dataset: per episode (HDF5 groups and attributes) and per transition (29 float32 observations, 9 float32
#: actions, a float64 reward, two flags, and HDF5's chunks); policies with noise also keep the clean actions
#: (``infos["clean_action"]``). Fitted 2026-12-01 to the HDF5 files of the collections above: 192 B a transition for
#: 700-step episodes without noise, 245 B for 178-step ones, 239-241 B for the noisy policies' ~600-step episodes.
BYTES_PER_EPISODE = 12_500
BYTES_PER_TRANSITION = 175
CLEAN_ACTION_BYTES_PER_TRANSITION = 45


def estimate(spec: CollectionSpec, n_episodes: int, workers: int) -> tuple[int, float | None, int]:
    """About how many transitions, seconds and bytes of disk ``n_episodes`` episodes of ``spec`` take with
    ``workers`` processes; a model policy's episodes are counted at the time limit and its time is ``None``."""
    steps = EPISODE_STEPS.get(spec.env_id, {}).get(spec.policy, envs.MAX_EPISODE_STEPS)
    transitions = n_episodes * steps
    seconds = None
    if spec.policy in POLICIES:
        rate = TRANSITIONS_PER_S["random" if spec.policy == RANDOM_POLICY else "controller"]
        seconds = WORKER_START_S + transitions / (rate * max(1, min(workers, os.cpu_count() or 1, n_episodes)))
    per_transition = BYTES_PER_TRANSITION + (CLEAN_ACTION_BYTES_PER_TRANSITION if spec.noise else 0)
    return transitions, seconds, n_episodes * BYTES_PER_EPISODE + transitions * per_transition


def plan(spec: CollectionSpec, dataset_id: str, workers: int, start: int, where: str | None = None) -> str:
    """The line a collection prints before it starts (``start`` episodes already collected; ``where`` they run)."""
    remaining = spec.n_episodes - start
    transitions, seconds, size = estimate(spec, remaining, workers)
    if seconds is None:
        cost = f"at most {format_size(size)} of disk ({transitions:,} transitions); a model policy's time is not estimated"
    else:
        cost = f"about {format_duration(seconds)} and {format_size(size)} of disk ({transitions:,} transitions)"
    with_workers = where or f"with {workers} worker{'s' if workers > 1 else ''}"
    if start == 0:
        return f"collecting {dataset_id}: {spec.n_episodes} episodes {with_workers}, {cost}"
    if remaining == 0:
        return f"resuming {dataset_id}: {start} of {spec.n_episodes} episodes already collected, none left"
    return (
        f"resuming {dataset_id}: {start} of {spec.n_episodes} episodes already collected; "
        f"the other {remaining} {with_workers}, {cost}"
    )


def format_duration(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, round(seconds))} s"
    if seconds < 90 * 60:
        return f"{round(seconds / 60)} min"
    return f"{seconds / 3600:.1f} h"


def format_size(size: float) -> str:
    if size < 1e6:
        return f"{max(1, round(size / 1e3))} kB"
    if size < 1e9:
        return f"{round(size / 1e6)} MB"
    return f"{size / 1e9:.1f} GB"


def check_space(files: DatasetFiles, needed: int, what: str) -> None:
    """One :class:`DatasetError` if the dataset's folder has less than ``needed`` bytes free."""
    folder = files.final.parent
    free = shutil.disk_usage(folder).free
    if free < needed:
        raise DatasetError(
            f"not enough disk space in {folder} for {what}: about {format_size(needed)} needed, {format_size(free)} free; "
            f"free some space (or set MINARI_DATASETS_PATH to another disk) and run the same command"
            + (f" (the {files.episodes_held()} episodes collected are kept)" if files.episodes_held() else "")
        )
