"""Which action dimensions move when CQL's actor turns from imitating a clone to following Q, and the critic's dQ/da.

Usage: python research/scripts/action_drift.py BC_MODEL.zip
           [--dataset-id ID] [--kwargs JSON] [--every N] [--probes N] [--probe-states N] [--log-dir DIR] [--threads N]

A :class:`sb3_cql.CQL` model on Panda-v0 in delta action mode (seed 1, the clone's network architecture) takes the
actor of ``BC_MODEL.zip`` and trains on ``--dataset-id`` (default ``sb3cql/Panda-v0/noisy-delta-v0``, collected first
if missing, as :class:`~sb3_cql.CQL` does for a standard id) with the keywords ``batch_size`` 128, ``bc_steps``
3000, ``reward_scale`` 4 and ``reward_bias`` -2, which ``--kwargs`` (a JSON object of CQL's keywords) overrides.
After the ``bc_steps`` warm-start steps (the critics trained, the actor still imitating) it prints the mean and the
mean absolute value of dQ/da per action dimension (the twin critics' minimum, at the deterministic policy's actions
over ``--probe-states`` data states, 4000 by default). Then ``--probes`` times (4) it makes ``--every`` (250) more
steps, now following Q, and prints the mean and mean absolute shift of the deterministic actions per dimension since
the warm start's end; last, dQ/da again. Lists have one value per action dimension (7 arm joints, then the two
fingers)::

    step 3000: dQ/da mean [...], |dQ/da| mean [...]
    step 3250: shift mean [...], |shift| mean [...]
    ...
    step 4000: dQ/da mean [...], |dQ/da| mean [...]

Nothing is saved but the training log (``progress.csv``, a row every 1,000 steps), in ``--log-dir``, by default a new
folder in the system's temporary directory (SB3's default: ``$SB3_LOGDIR`` or ``/tmp/SB3-DATE``); the line
``Logging to DIR`` names it. Torch runs ``--threads`` threads (1 by default).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch as th
from _cli import cql_from_clone, cql_keywords, positive_int
from stable_baselines3.common.logger import configure

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL
from sb3_cql.data import DatasetError

DEFAULT_DATASET = "sb3cql/Panda-v0/noisy-delta-v0"
DEFAULT_KWARGS = {"batch_size": 128, "bc_steps": 3000, "reward_scale": 4.0, "reward_bias": -2.0}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/action_drift.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("bc_model", metavar="BC_MODEL.zip", help="a saved sb3_cql.BC model (delta action mode)")
    parser.add_argument(
        "--dataset-id", metavar="ID", default=DEFAULT_DATASET, help=f"Minari id of CQL's data (default {DEFAULT_DATASET})"
    )
    parser.add_argument("--kwargs", metavar="JSON", type=cql_keywords, default="{}",
                        help=f"JSON object of CQL keywords over the defaults {json.dumps(DEFAULT_KWARGS)}")  # fmt: skip
    parser.add_argument(
        "--every", metavar="N", type=positive_int, default=250, help="Q-following steps between probes (default 250)"
    )
    parser.add_argument("--probes", metavar="N", type=positive_int, default=4, help="probes after the warm start (default 4)")
    parser.add_argument("--probe-states", metavar="N", type=positive_int, default=4000, help="states probed (default 4000)")
    parser.add_argument(
        "--log-dir", metavar="DIR", default=None, help="folder of the CSV log (default: a new temporary folder)"
    )
    parser.add_argument("--threads", metavar="N", type=positive_int, default=1, help="torch threads (default 1)")
    return parser.parse_args(argv)


def rounded(values: th.Tensor) -> list[float]:
    return np.round(values.double().cpu().numpy(), 3).tolist()


class Probe:
    """The deterministic policy's actions and the critic's dQ/da at a fixed sample of data states."""

    def __init__(self, model: CQL, n_states: int) -> None:
        self.model = model
        self.observations = model.replay_buffer.sample(n_states).observations

    def actions(self) -> th.Tensor:
        with th.no_grad():
            return self.model.actor(self.observations, deterministic=True)

    def q_gradient(self) -> str:
        """The mean and mean absolute dQ/da per dimension of the twin critics' minimum at the policy's actions."""
        actions = self.actions().requires_grad_(True)
        q_values = th.cat(self.model.critic(self.observations, actions), 1).min(1).values.sum()
        (gradient,) = th.autograd.grad(q_values, actions)
        return f"dQ/da mean {rounded(gradient.mean(0))}, |dQ/da| mean {rounded(gradient.abs().mean(0))}"


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = cql_from_clone(args.bc_model, args.dataset_id, {**DEFAULT_KWARGS, **args.kwargs})
    except DatasetError as error:
        sys.exit(f"error: {error}")
    model.set_logger(configure(args.log_dir, ["csv"]))
    print(f"Logging to {model.logger.get_dir()}", flush=True)
    probe = Probe(model, args.probe_states)
    model.learn(model.bc_steps)
    start = probe.actions()
    print(f"step {model.num_timesteps}: {probe.q_gradient()}", flush=True)
    for _ in range(args.probes):
        model.learn(args.every, reset_num_timesteps=False)
        shift = probe.actions() - start
        shifts = f"shift mean {rounded(shift.mean(0))}, |shift| mean {rounded(shift.abs().mean(0))}"
        print(f"step {model.num_timesteps}: {shifts}", flush=True)
    print(f"step {model.num_timesteps}: {probe.q_gradient()}", flush=True)


if __name__ == "__main__":
    main()
