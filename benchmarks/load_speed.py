"""Time and memory of loading a dataset into SB3's ReplayBuffer.

    python benchmarks/load_speed.py [--dataset-id sb3cql/Panda-v0/pid-v0]

Reports the wall time of ``fill_replay_buffer`` (goal <= 30 s for 3M transitions), the buffer's arrays, and the
process's peak resident memory above what it held before loading: the goal is no more than the buffer's arrays
plus one episode (no second full copy of the data).
"""

from __future__ import annotations

import argparse
import resource
import time

from stable_baselines3.common.buffers import ReplayBuffer  # noqa: F401  (torch is loaded before measuring)

import envs  # noqa: F401  (registers the tasks)
from sb3_cql.data import fill_replay_buffer, load_dataset


def resident_mib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset-id", default="sb3cql/Panda-v0/pid-v0")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset_id)
    env = dataset.recover_environment()
    before = resident_mib()
    start = time.perf_counter()
    buffer = fill_replay_buffer(dataset, env.observation_space, env.action_space)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    arrays = sum(
        getattr(buffer, name).nbytes
        for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
    )
    episode = arrays / dataset.total_episodes
    print(f"{args.dataset_id}: {dataset.total_episodes} episodes, {buffer.size()} transitions")
    print(f"load: {seconds:.1f} s ({buffer.size() / seconds:,.0f} transitions/s)")
    print(f"buffer arrays: {arrays / 2**20:.0f} MiB; one episode: ~{episode / 2**10:.0f} KiB")
    print(f"peak resident memory above the start of loading: {peak - before:.0f} MiB")


if __name__ == "__main__":
    main()
