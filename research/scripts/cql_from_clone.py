"""CQL with its actor started from a trained BC model, its success rate measured every K gradient steps.

Usage: python research/scripts/cql_from_clone.py BC_MODEL.zip STEPS K KWARGS_JSON [DATASET_ID]
           [--eval-episodes N] [--eval-seed SEED] [--log-dir DIR] [--threads N]

A :class:`sb3_cql.CQL` model on Panda-v0 in delta action mode (seed 1) takes the actor of ``BC_MODEL.zip`` (weights
and observation statistics) and makes ``STEPS`` gradient steps on ``DATASET_ID`` (default
``sb3cql/Panda-v0/noisy-delta-v0``, collected first if missing, as :class:`~sb3_cql.CQL` does for a standard id).
``KWARGS_JSON`` is a JSON object of CQL's keywords, e.g.
``'{"batch_size": 128, "bc_steps": 3000, "reward_scale": 4.0, "reward_bias": -2.0, "actor_bc_weight": 4.0}'``;
``policy_kwargs`` defaults to the clone's network architecture. Two more keys select a measured variant of the
critic's backup, not a CQL keyword (at most one of them):

- ``"clip_backup": true``: the next-state values are clamped to the returns the rewards allow,
  ``min_r / (1 - gamma)`` to ``max_r / (1 - gamma)``, ``min_r`` and ``max_r`` the 0/1 rewards after ``reward_scale``
  and ``reward_bias``;
- ``"mean_backup": true``: the backup scores the policy's mean action at s' (TD3's target) instead of a sample.

Before the first step and after every ``K`` steps it prints the step, the deterministic policy's success rate on
Panda-v0 (``--eval-episodes`` episodes, 10 by default, the env reset with ``--eval-seed``, 1000 by default) and,
after training steps, the policy's mean pre-tanh standard deviation per action dimension over 512 sampled states::

    step 0: success rate 1.000
    step 1000: success rate 1.000, policy std [0.9, 0.88, ..., 5.2]

The run's folder is ``--log-dir``/TIME-PID (``--log-dir`` is ``cql_from_clone_logs`` in the current directory by
default; the line ``Logging to DIR`` names the run's folder): ``progress.csv`` holds CQL's ``train/`` diagnostics
(``cql_q_data``, ``cql_q_policy``, ``cql_gap``, ...), one row every K steps, and the final model is saved as
``model.zip`` in it (the last line, ``saved DIR/model.zip``), to evaluate with
``python -m sb3_cql.evaluate DIR/model.zip --algo cql --env-kwargs "action_mode:'delta'"``. Torch runs ``--threads``
threads (1 by default). The documentation's "What we learned" page gives the findings of these runs.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import _cli
import torch as th
from _cli import positive_int, train
from stable_baselines3.common.logger import configure
from stable_baselines3.sac.policies import LOG_STD_MIN

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL
from sb3_cql.data import DatasetError
from sb3_cql.evaluate import success_rate

ENV_ID = "Panda-v0"
ENV_KWARGS = {"action_mode": "delta"}
DEFAULT_DATASET = "sb3cql/Panda-v0/noisy-delta-v0"
#: Keys of KWARGS_JSON that select a backup variant (``VARIANTS``) rather than pass a CQL keyword.
VARIANT_KEYS = ("clip_backup", "mean_backup")


class ClippedBackupCQL(CQL):
    """CQL whose backup clamps the next-state values to the returns the rewards allow, ``min_r / (1 - gamma)`` to
    ``max_r / (1 - gamma)``, with ``min_r`` and ``max_r`` the 0/1 rewards after ``reward_scale`` and ``reward_bias``."""

    def next_state_values(self, *args: Any, **kwargs: Any) -> th.Tensor:
        values = super().next_state_values(*args, **kwargs)
        low, high = sorted((self.reward_bias, self.reward_scale + self.reward_bias))
        return values.clamp(low / (1 - self.gamma), high / (1 - self.gamma))


class MeanBackupCQL(CQL):
    """CQL whose backup scores the policy's mean action at s' (TD3's target) instead of a sample: Q of the
    deterministic policy that is evaluated, not of its noisy samples."""

    def next_state_values(
        self, next_observations: th.Tensor, next_policy: tuple[th.Tensor, th.Tensor], ent_coef: th.Tensor
    ) -> th.Tensor:
        mean_actions, log_std = next_policy
        narrowest = (mean_actions, th.full_like(log_std, LOG_STD_MIN))
        return super().next_state_values(next_observations, narrowest, ent_coef)


VARIANTS = {"clip_backup": ClippedBackupCQL, "mean_backup": MeanBackupCQL}


def cql_keywords(text: str) -> dict[str, Any]:
    """KWARGS_JSON: a JSON object of CQL's keywords and the variant keys, at most one of those."""
    kwargs = _cli.cql_keywords(text, extra_keys=VARIANT_KEYS)
    if sum(bool(kwargs.get(key)) for key in VARIANT_KEYS) > 1:
        raise argparse.ArgumentTypeError(f"at most one of {', '.join(VARIANT_KEYS)}")
    return kwargs


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/cql_from_clone.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("bc_model", metavar="BC_MODEL.zip", help="a saved sb3_cql.BC model (delta action mode)")
    parser.add_argument("steps", metavar="STEPS", type=int, help="gradient steps in all")
    parser.add_argument("every", metavar="K", type=positive_int, help="gradient steps between two evaluations")
    parser.add_argument("kwargs", metavar="KWARGS_JSON", type=cql_keywords, help="JSON object of CQL keywords")
    parser.add_argument("dataset_id", metavar="DATASET_ID", nargs="?", default=DEFAULT_DATASET,
                        help=f"Minari id of CQL's data (default {DEFAULT_DATASET})")  # fmt: skip
    parser.add_argument(
        "--eval-episodes", metavar="N", type=positive_int, default=10, help="episodes per evaluation (default 10)"
    )
    parser.add_argument(
        "--eval-seed", metavar="SEED", type=int, default=1000, help="seed of the evaluation env (default 1000)"
    )
    parser.add_argument("--log-dir", metavar="DIR", default="cql_from_clone_logs",
                        help="folder of the runs' folders TIME-PID (default cql_from_clone_logs)")  # fmt: skip
    parser.add_argument("--threads", metavar="N", type=positive_int, default=1, help="torch threads (default 1)")
    return parser.parse_args(argv)


def cql_from_clone(bc_model: str, dataset_id: str, kwargs: dict[str, Any]) -> CQL:
    """A CQL model (or a variant's, per ``kwargs``) on ``dataset_id`` whose actor is the saved clone's."""
    kwargs = dict(kwargs)
    variant = next((VARIANTS[key] for key in VARIANT_KEYS if kwargs.pop(key, False)), CQL)
    return _cli.cql_from_clone(bc_model, dataset_id, kwargs, algorithm=variant, env_id=ENV_ID)


def policy_std(model: CQL, n_states: int = 512) -> list[float]:
    """The policy's mean pre-tanh standard deviation per action dimension over ``n_states`` states of the data."""
    data = model.replay_buffer.sample(n_states)
    with th.no_grad():
        _, log_std, _ = model.actor.get_action_dist_params(data.observations)
    return log_std.exp().mean(0).double().cpu().numpy().round(2).tolist()


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = cql_from_clone(args.bc_model, args.dataset_id, args.kwargs)
    except DatasetError as error:
        sys.exit(f"error: {error}")
    run_dir = Path(args.log_dir) / f"{int(time.time())}-{os.getpid()}"  # two runs started together get their own
    model.set_logger(configure(str(run_dir), ["csv"]))
    print(f"Logging to {run_dir}", flush=True)

    def success() -> str:
        rate = success_rate(model, ENV_ID, n_episodes=args.eval_episodes, seed=args.eval_seed, env_kwargs=ENV_KWARGS)
        return f"success rate {rate:.3f}"

    print(f"step 0: {success()}", flush=True)
    done = 0
    while done < args.steps:
        done += train(model, min(args.every, args.steps - done))
        print(f"step {done}: {success()}, policy std {policy_std(model)}", flush=True)
    model.save(run_dir / "model.zip")
    print(f"saved {run_dir / 'model.zip'}", flush=True)


if __name__ == "__main__":
    main()
