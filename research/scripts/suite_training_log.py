"""Our CQL on one of the offline suite's data sets with its training log kept: ``OUT/progress.csv`` every 500
gradient steps (``train/cql_alpha_prime``, ``train/cql_gap``, the critics' values), the model and its score.

    python research/scripts/suite_training_log.py SUITE_OUT DATASET OUT [--keywords JSON] [--seed 0] [--steps 10000]

``SUITE_OUT`` is the suite's folder (its data sets in ``SUITE_OUT/data``, made there the first time); the model is
trained and scored as ``benchmarks/offline_suite.py`` does (20 episodes on env seeds 10000 onwards).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.logger import configure

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
import offline_suite as suite  # noqa: E402

from sb3_cql import CQL  # noqa: E402
from sb3_cql.common import KeywordError  # noqa: E402


def cql_keywords(text: str) -> dict:
    """``--keywords``: a JSON object of CQL's keywords."""
    try:
        keywords = json.loads(text)
    except json.JSONDecodeError:
        raise argparse.ArgumentTypeError(f"not JSON: {text!r}") from None
    if not isinstance(keywords, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object, got {text!r}")
    try:
        CQL.refuse_unknown_keywords(keywords)
    except KeywordError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return keywords


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python research/scripts/suite_training_log.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("suite_out", type=Path)
    parser.add_argument("dataset", choices=sorted(suite.DATASETS))
    parser.add_argument("out", type=Path)
    parser.add_argument("--keywords", type=cql_keywords, default={}, help="CQL's keywords, as JSON")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=10_000)
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    task = suite.task_of(args.dataset)
    data = suite.load_data(args.dataset, args.suite_out / "data")
    env = gym.make(task.env_id)
    model = CQL("MlpPolicy", env, dataset=suite.replay_buffer(data, env), seed=args.seed, **args.keywords)
    model.set_logger(configure(str(args.out), ["csv", "stdout"]))
    model.learn(args.steps, log_interval=500)
    model.save(args.out / "model.zip")
    returns, successes = suite.evaluate(lambda o: model.predict(o, deterministic=True)[0], task.env_id, 20)
    score = float(np.mean(successes if task.scored_by == "success" else returns))
    record = {"score": score, "returns": [float(r) for r in returns], "successes": [bool(s) for s in successes]}
    suite.write_json(args.out / "score.json", record)  # whole or not at all
    print(f"{args.dataset}: {score:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
