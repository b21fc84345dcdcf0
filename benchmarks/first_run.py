"""A new user's first run, timed: the README's main command from an empty dataset folder to an evaluated policy.

    python benchmarks/first_run.py [--algo cql] [--env Panda-v0] [--zoo-args "..."] [--eval-seeds 50000-50099]
                                   [--tasks Panda-v0 PandaForce-v0 PandaPerturbed-v0] [--workdir DIR]

Runs ``python -m rl_zoo3.train --algo ALGO --env ENV -f logs`` (plus ``--zoo-args``) in ``--workdir`` (a fresh
temporary folder by default) with ``MINARI_DATASETS_PATH`` pointing to an empty folder inside it, exactly as a
first run on a new machine: the config's dataset is collected, loaded, and the model trained with its evaluations.
Then the run's last model (``ENV.zip``) and its best evaluated model (``best_model.zip``) are evaluated with
``python -m sb3_cql.evaluate --seeds`` on ``--tasks`` (episodes the training never saw: the zoo evaluates with the
training seed's episodes).

Prints the wall time of each stage: collection (until the dataset is complete on disk), loading and training (the
rest of the zoo run, evaluations during training included), the final evaluations; and the success rates.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

# The tasks, without importing the package (whose envs start PyBullet): a fixed list for the defaults.
TASKS = ("Panda-v0", "PandaForce-v0", "PandaPerturbed-v0")


def _minutes(seconds: float) -> str:
    return f"{int(seconds // 60)} min {seconds % 60:04.1f} s"


def _watch_collection(datasets: Path, done: threading.Event, finished: dict[str, float], start: float) -> None:
    """Note when the first complete dataset appears under ``datasets``: a collection writes into a hidden
    ``.<name>.partial`` folder (whose ``metadata.json`` is there from its first episodes) and renames it when done."""
    while not done.is_set():
        if any(not path.parts[-3].startswith(".") for path in datasets.glob("*/*/*/data/metadata.json")):
            finished["collection"] = time.perf_counter() - start
            return
        time.sleep(0.5)


def evaluate(workdir: Path, env: dict[str, str], model: Path, algo: str, tasks: list[str], seeds: str) -> dict[str, str]:
    """Success rate on each task, as ``python -m sb3_cql.evaluate`` prints it."""
    command = [sys.executable, "-m", "sb3_cql.evaluate", str(model), "--algo", algo, "--env", *tasks, "--seeds", seeds]
    result = subprocess.run(command, cwd=workdir, env=env, capture_output=True, text=True, check=True)
    return {line.split(":")[0]: line.split("success rate ")[1].split()[0] for line in result.stdout.splitlines() if
            "success rate" in line}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="cql")
    parser.add_argument("--env", default="Panda-v0")
    parser.add_argument("--zoo-args", default="", help='more rl_zoo3.train arguments, e.g. "--seed 1"')
    parser.add_argument("--eval-seeds", default="50000-50099", help="sb3_cql.evaluate --seeds of the final evaluations")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--workdir", default=None, help="folder of the run (default: a new temporary folder)")
    args = parser.parse_args()

    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="first-run-")).resolve()
    datasets = workdir / "datasets"
    if datasets.exists() and any(datasets.iterdir()):
        parser.error(f"{datasets} is not empty: a first run starts without datasets")
    datasets.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "MINARI_DATASETS_PATH": str(datasets), "MPLBACKEND": "Agg"}
    command = [sys.executable, "-m", "rl_zoo3.train", "--algo", args.algo, "--env", args.env, "-f", "logs",
               *shlex.split(args.zoo_args)]  # fmt: skip
    print(f"in {workdir}: {' '.join(command[1:])}", flush=True)

    stages: dict[str, float] = {}
    done = threading.Event()
    start = time.perf_counter()
    watcher = threading.Thread(target=_watch_collection, args=(datasets, done, stages, start), daemon=True)
    watcher.start()
    with open(workdir / "train.log", "w") as log:
        returncode = subprocess.run(command, cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT).returncode
    done.set()
    total_train = time.perf_counter() - start
    if returncode != 0:
        sys.exit(f"the run failed (exit {returncode}): see {workdir / 'train.log'}")
    collection = stages.get("collection", 0.0)  # 0: the dataset was not collected (it was already there)

    (run,) = sorted((workdir / "logs" / args.algo).glob(f"{args.env}_*"))
    rates, evaluation_start = {}, time.perf_counter()
    for name in (f"{args.env}.zip", "best_model.zip"):
        if (run / name).is_file():
            rates[name] = evaluate(workdir, env, run / name, args.algo, args.tasks, args.eval_seeds)
    evaluation = time.perf_counter() - evaluation_start

    print(f"collection: {_minutes(collection)}")
    print(f"loading and training (evaluations during training included): {_minutes(total_train - collection)}")
    print(f"main command in all: {_minutes(total_train)}")
    models = f"{len(rates)} models x {len(args.tasks)} tasks, seeds {args.eval_seeds}"
    print(f"final evaluations ({models}): {_minutes(evaluation)}")
    for name, by_task in rates.items():
        print(f"{run.relative_to(workdir) / name}: " + ", ".join(f"{task} {rate}" for task, rate in by_task.items()))


if __name__ == "__main__":
    main()
