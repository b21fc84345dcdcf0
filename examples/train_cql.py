"""Train CQL offline on a PD-controller dataset of Panda-v0, evaluating online, with TensorBoard logs.

    python -m sb3_cql.data collect --env Panda-v0 --policy pid --episodes 10000 --workers 2   # once
    python examples/train_cql.py --timesteps 30000 --eval-freq 1000 --tensorboard-log tb
    tensorboard --logdir tb

The best model by evaluation success is saved in ``--log-dir`` (``best_model.zip``), with ``evaluations.npz``.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.monitor import Monitor

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Panda-v0")
    parser.add_argument("--dataset-id", default="sb3cql/Panda-v0/pid-v0")
    parser.add_argument("--timesteps", type=int, default=30_000, help="gradient steps")
    parser.add_argument("--eval-freq", type=int, default=1000, help="gradient steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--log-dir", default="logs/cql")
    parser.add_argument("--tensorboard-log", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cql-alpha", type=float, default=10.0)
    parser.add_argument("--cql-target-action-gap", type=float, default=None, help="learn the Lagrange multiplier")
    parser.add_argument("--bc-steps", type=int, default=0, help="behaviour-cloning warm start (gradient steps)")
    args = parser.parse_args()

    model = CQL("MlpPolicy", args.env, dataset=args.dataset_id, tensorboard_log=args.tensorboard_log, seed=args.seed,
                cql_alpha=args.cql_alpha, cql_target_action_gap=args.cql_target_action_gap, bc_steps=args.bc_steps,
                policy_kwargs={"net_arch": [256, 256, 256]}, verbose=1)  # fmt: skip
    eval_env = Monitor(gym.make(args.env), info_keywords=("is_success",))
    eval_env.reset(seed=args.seed)
    evaluation = EvalCallback(eval_env, eval_freq=args.eval_freq, n_eval_episodes=args.eval_episodes,
                              best_model_save_path=args.log_dir, log_path=args.log_dir)  # fmt: skip
    model.learn(args.timesteps, callback=evaluation, progress_bar=True)
    model.save(f"{args.log_dir}/final_model")
    rates = [float(np.mean(successes)) for successes in evaluation.evaluations_successes]
    print(f"evaluation success rates: {rates}; the best model is {args.log_dir}/best_model.zip")


if __name__ == "__main__":
    main()
