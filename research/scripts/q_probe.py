"""Train CQL briefly, then compare its Q-values at the data's actions, at perturbed data actions and at the policy's.

Usage: python research/scripts/q_probe.py STEPS KWARGS_JSON
           [--dataset-id ID] [--probe-states N] [--log-dir DIR] [--threads N]

A :class:`sb3_cql.CQL` model on Panda-v0 in delta action mode (seed 1, 3 x 256 networks unless ``policy_kwargs``
says otherwise) makes ``STEPS`` gradient steps on ``--dataset-id`` (default ``sb3cql/Panda-v0/x-noisy-delta-v0``,
which must exist). ``KWARGS_JSON`` is a JSON object of CQL's keywords, e.g.
``'{"batch_size": 128, "bc_steps": 10000, "reward_scale": 4.0, "reward_bias": -2.0}'``. Then, over
``--probe-states`` transitions sampled from the data (2000 by default), it prints the mean over states of the twin
critics' minimum Q at:

- the data's actions (``Q data``), and the data's gripper values seen (``gripper data values``, up to 10);
- the data's actions with the two gripper dimensions scaled by 0.99, 0.97, 0.9 and 0.5 (``Q gripper x 0.99``, ...):
  how sharply Q falls off the data's saturated gripper commands;
- the data's actions with N(0, 0.05) noise on the arm dimensions (``Q arm +N(0,0.05)``);
- the policy's deterministic (mean) and sampled actions, with its mean pre-tanh standard deviation per dimension
  (``Q policy mean X, Q policy sample Y, policy std [...]``), and its mean actions with the data's gripper values
  (``Q policy mean with data gripper``).

One line each, e.g. ``Q data -162.4``. Nothing is saved but the training log (``progress.csv``, a row
every 1,000 steps), in ``--log-dir``, by default a new folder in the system's temporary directory (SB3's default:
``$SB3_LOGDIR`` or ``/tmp/SB3-DATE``); the line ``Logging to DIR`` names it. Torch runs ``--threads`` threads (1 by
default).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import gymnasium as gym
import torch as th
from _cli import cql_keywords, positive_int
from stable_baselines3.common.logger import configure

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL
from sb3_cql.data import DatasetError

DEFAULT_DATASET = "sb3cql/Panda-v0/x-noisy-delta-v0"
#: Factors applied to the data's gripper actions.
GRIPPER_SCALES = (0.99, 0.97, 0.9, 0.5)
#: Standard deviation of the noise added to the data's arm actions.
ARM_NOISE = 0.05


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/q_probe.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("steps", metavar="STEPS", type=int, help="gradient steps")
    parser.add_argument("kwargs", metavar="KWARGS_JSON", type=cql_keywords, help="JSON object of CQL keywords")
    parser.add_argument(
        "--dataset-id", metavar="ID", default=DEFAULT_DATASET, help=f"Minari id of CQL's data (default {DEFAULT_DATASET})"
    )
    parser.add_argument("--probe-states", metavar="N", type=positive_int, default=2000, help="states probed (default 2000)")
    parser.add_argument(
        "--log-dir", metavar="DIR", default=None, help="folder of the CSV log (default: a new temporary folder)"
    )
    parser.add_argument("--threads", metavar="N", type=positive_int, default=1, help="torch threads (default 1)")
    return parser.parse_args(argv)


def trained_cql(steps: int, dataset_id: str, kwargs: dict[str, Any], log_dir: str | None) -> CQL:
    """A CQL model trained for ``steps`` gradient steps on ``dataset_id``, its CSV log in ``log_dir``."""
    kwargs = {**kwargs, "policy_kwargs": {"net_arch": [256, 256, 256], **kwargs.get("policy_kwargs", {})}}
    model = CQL("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), dataset=dataset_id, seed=1, **kwargs)
    model.set_logger(configure(log_dir, ["csv"]))
    print(f"Logging to {model.logger.get_dir()}", flush=True)
    return model.learn(steps)


def probe(model: CQL, n_states: int) -> None:
    """Print Q at the data's actions, perturbations of them and the policy's actions, at ``n_states`` data states."""
    data = model.replay_buffer.sample(n_states)
    observations, actions = data.observations, data.actions

    def q(candidates: th.Tensor) -> float:
        with th.no_grad():
            return th.cat(model.critic(observations, candidates), 1).min(1).values.mean().item()

    print("gripper data values", actions[:, -2:].unique()[:10].tolist())
    print("Q data", q(actions))
    for scale in GRIPPER_SCALES:
        scaled = actions.clone()
        scaled[:, -2:] *= scale
        print("Q gripper x", scale, q(scaled))
    noisy = actions.clone()
    noisy[:, :-2] += ARM_NOISE * th.randn_like(noisy[:, :-2])
    print(f"Q arm +N(0,{ARM_NOISE})", q(noisy.clamp(-1, 1)))
    with th.no_grad():
        mean, log_std, _ = model.actor.get_action_dist_params(observations)
        sampled, _ = model.actor.action_log_prob(observations)
    print(f"Q policy mean {q(th.tanh(mean))}, Q policy sample {q(sampled)}, policy std {log_std.exp().mean(0).tolist()}")
    with_data_gripper = th.tanh(mean)
    with_data_gripper[:, -2:] = actions[:, -2:]
    print("Q policy mean with data gripper", q(with_data_gripper))


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = trained_cql(args.steps, args.dataset_id, args.kwargs, args.log_dir)
    except DatasetError as error:
        sys.exit(f"error: {error}")
    probe(model, args.probe_states)


if __name__ == "__main__":
    main()
