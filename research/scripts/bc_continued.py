"""A trained BC actor trained on with BC at a constant learning rate, its success rate measured every K steps.

Usage: python research/scripts/bc_continued.py BC_MODEL.zip STEPS K LR BATCH DATASET_ID
           [--eval-episodes N] [--eval-seed SEED] [--log-dir DIR] [--threads N]

A new :class:`sb3_cql.BC` model on Panda-v0 in delta action mode (seed 1, the clone's network architecture) starts
from the actor of ``BC_MODEL.zip`` and makes ``STEPS`` behaviour-cloning gradient steps on ``DATASET_ID`` at the
constant learning rate ``LR`` with minibatches of ``BATCH``. Before the first step and after every ``K`` steps it
prints the step and the deterministic policy's success rate on Panda-v0 (``--eval-episodes`` episodes, 10 by
default, the env reset with ``--eval-seed``, 1000 by default)::

    step 0: success rate 1.000
    step 1000: success rate 0.900

It shows whether a clone stays a working policy under further imitation at a rate that does not decay, the
comparison for CQL started from the same clone (``research/scripts/cql_from_clone.py``).

The training log (``progress.csv``, one row every K steps) goes to ``--log-dir``, by default a new folder in the
system's temporary directory (SB3's default: ``$SB3_LOGDIR`` or ``/tmp/SB3-DATE``); the line ``Logging to DIR`` names
it. No model is saved. Torch runs ``--threads`` threads (1 by default).
"""

from __future__ import annotations

import argparse
import sys

import gymnasium as gym
import torch as th
from _cli import positive_int, train
from stable_baselines3.common.logger import configure

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import BC
from sb3_cql.data import DatasetError
from sb3_cql.evaluate import success_rate

ENV_ID = "Panda-v0"
ENV_KWARGS = {"action_mode": "delta"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/bc_continued.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("bc_model", metavar="BC_MODEL.zip", help="a saved sb3_cql.BC model (delta action mode)")
    parser.add_argument("steps", metavar="STEPS", type=int, help="gradient steps in all")
    parser.add_argument("every", metavar="K", type=positive_int, help="gradient steps between two evaluations")
    parser.add_argument("learning_rate", metavar="LR", type=float, help="the constant learning rate")
    parser.add_argument("batch_size", metavar="BATCH", type=positive_int, help="minibatch size")
    parser.add_argument("dataset_id", metavar="DATASET_ID", help="Minari id of the data to imitate")
    parser.add_argument(
        "--eval-episodes", metavar="N", type=positive_int, default=10, help="episodes per evaluation (default 10)"
    )
    parser.add_argument(
        "--eval-seed", metavar="SEED", type=int, default=1000, help="seed of the evaluation env (default 1000)"
    )
    parser.add_argument(
        "--log-dir", metavar="DIR", default=None, help="folder of the CSV log (default: a new temporary folder)"
    )
    parser.add_argument("--threads", metavar="N", type=positive_int, default=1, help="torch threads (default 1)")
    return parser.parse_args(argv)


def continued_clone(args: argparse.Namespace) -> BC:
    """A BC model on ``args.dataset_id`` whose actor is the saved clone's."""
    clone = BC.load(args.bc_model)
    model = BC(
        "MlpPolicy",
        gym.make(ENV_ID, **ENV_KWARGS),
        dataset=args.dataset_id,
        learning_rate=args.learning_rate,
        batch_size=args.batch_size,
        policy_kwargs=dict(net_arch=clone.policy_kwargs["net_arch"]),
        seed=1,
    )
    model.actor.load_state_dict(clone.actor.state_dict())
    model.set_logger(configure(args.log_dir, ["csv"]))
    print(f"Logging to {model.logger.get_dir()}", flush=True)
    return model


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = continued_clone(args)
    except DatasetError as error:
        sys.exit(f"error: {error}")

    def report(step: int) -> None:
        rate = success_rate(model, ENV_ID, n_episodes=args.eval_episodes, seed=args.eval_seed, env_kwargs=ENV_KWARGS)
        print(f"step {step}: success rate {rate:.3f}", flush=True)

    report(0)
    done = 0
    while done < args.steps:
        done += train(model, min(args.every, args.steps - done))
        report(done)


if __name__ == "__main__":
    main()
