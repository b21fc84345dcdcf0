"""Ray's overhead: the same work in the local pool and on a local Ray cluster of two nodes, side by side.

    python benchmarks/cluster_speed.py [--episodes 200] [--steps 300]

1. A collection of ``--episodes`` noisy-regrasp episodes of Panda-v0 (delta actions): ``--workers 2`` against
   ``--ray`` on a cluster of two nodes of one CPU each, started here (``ray.cluster_utils.Cluster``).
2. A tiny protocol (BC, 1 seed, ``--steps`` training steps, 2 evaluation episodes a task) on a 4-episode dataset:
   ``--workers 2`` against ``--ray`` on the same cluster.

Each is one ``python -m`` command, timed from start to end (so Ray's connection and task start-up count); the
datasets and results go to a temporary folder. The overhead per unit is the difference of the wall times over the
units run (collection: chunks of 50 episodes; protocol: 1 training and 3 evaluations).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed(command: list[str], env: dict[str, str], cwd: Path) -> float:
    start = time.perf_counter()
    result = subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()

    from ray.cluster_utils import Cluster

    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)
        env = {**os.environ, "MINARI_DATASETS_PATH": str(root / "datasets"), "MPLBACKEND": "Agg"}
        os.environ.update(env)  # the cluster's nodes (and so its tasks) see the same datasets folder
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        try:
            data = [sys.executable, "-m", "sb3_cql.data", "collect", "--policy", "noisy-regrasp", "--action-mode",
                    "delta", "--episodes", str(args.episodes)]  # fmt: skip
            local = timed([*data, "--workers", "2", "--dataset-id", "bench/Panda-v0/local-v0"], env, root)
            ray = timed([*data, "--ray", cluster.address, "--dataset-id", "bench/Panda-v0/ray-v0"], env, root)
            chunks = -(-args.episodes // 50)
            print(f"collection of {args.episodes} episodes: local pool of 2 workers {local:.1f} s, Ray cluster of 2 "
                  f"nodes {ray:.1f} s: {ray / local:.2f}x; {(ray - local) / chunks:+.2f} s per chunk of 50 "
                  "episodes")  # fmt: skip

            timed([*data[:-1], "4", "--dataset-id", "sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0"], env, root)
            protocol = [sys.executable, "-m", "sb3_cql.protocol", "--algos", "bc", "--seeds", "1", "--n-timesteps",
                        str(args.steps), "--eval-freq", str(args.steps), "--eval-episodes", "1", "--episodes", "2",
                        "--save-freq", str(args.steps), "--no-filmstrips",
                        "--zoo-args", "--hyperparams batch_size:64 policy_kwargs:dict(net_arch=[32,32])"]  # fmt: skip
            local = timed([*protocol, "--workers", "2", "--results-dir", str(root / "local")], env, root)
            ray = timed([*protocol, "--ray", cluster.address, "--results-dir", str(root / "ray")], env, root)
            print(f"tiny protocol (BC, 1 seed, {args.steps} steps, 3 tasks x 2 episodes): local pool of 2 workers "
                  f"{local:.1f} s, Ray cluster of 2 nodes {ray:.1f} s: {ray / local:.2f}x; {(ray - local) / 4:+.2f} s per "
                  "unit (1 training, 3 evaluations)")  # fmt: skip
        finally:
            cluster.shutdown()


if __name__ == "__main__":
    main()
