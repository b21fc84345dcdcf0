"""Speed of dataset collection: one worker against two on the same episodes, then a full collection.

    python benchmarks/collect_speed.py [--sample-episodes 400] [--episodes 10000] [--keep]

1. ``--sample-episodes`` PD episodes of Panda-v0 (seeds 0..n-1) collected with 1 worker, then the same episodes
   with 2 workers, into a temporary folder: transitions/s of each and their ratio (goal >= 1.7).
2. ``--episodes`` with 2 workers, timed (goal <= 15 minutes for 10,000). With ``--keep`` this is the default
   dataset ``sb3cql/Panda-v0/pid-v0`` in Minari's own folder (``MINARI_DATASETS_PATH``); otherwise a temporary one.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from sb3_cql.data import CollectionSpec, collect_dataset


def timed_collection(spec: CollectionSpec, dataset_id: str, workers: int) -> tuple[float, int]:
    start = time.perf_counter()
    dataset = collect_dataset(spec, dataset_id, workers=workers, overwrite=True)
    return time.perf_counter() - start, dataset.total_steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sample-episodes", type=int, default=400)
    parser.add_argument("--episodes", type=int, default=10_000)
    parser.add_argument("--keep", action="store_true", help="write the full collection as sb3cql/Panda-v0/pid-v0")
    args = parser.parse_args()

    default_root = os.environ.get("MINARI_DATASETS_PATH")
    with tempfile.TemporaryDirectory() as scratch:
        os.environ["MINARI_DATASETS_PATH"] = scratch
        sample = CollectionSpec(n_episodes=args.sample_episodes)
        rates = {}
        for workers in (1, 2):
            seconds, steps = timed_collection(sample, f"bench/Panda-v0/pid-{workers}w-v0", workers)
            rates[workers] = steps / seconds
            print(f"{args.sample_episodes} episodes, {workers} worker(s): {seconds:.1f} s, {rates[workers]:.0f} transitions/s")
        print(f"2 workers / 1 worker: {rates[2] / rates[1]:.2f}x")

        if args.keep:
            if default_root is None:
                del os.environ["MINARI_DATASETS_PATH"]
            else:
                os.environ["MINARI_DATASETS_PATH"] = default_root
        seconds, steps = timed_collection(CollectionSpec(n_episodes=args.episodes), "sb3cql/Panda-v0/pid-v0", 2)
        print(f"{args.episodes} episodes, 2 workers: {seconds / 60:.1f} min, {steps} transitions, {steps / seconds:.0f}/s")


if __name__ == "__main__":
    main()
