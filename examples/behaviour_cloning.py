"""Behaviour cloning on a dataset: can its actions be imitated? A quick check of a dataset before offline RL.

    python -m sb3_cql.data collect --policy noisy --action-mode delta --episodes 300 --workers 2 \\
        --dataset-id sb3cql/Panda-v0/noisy300-delta-v0
    python examples/behaviour_cloning.py --dataset-id sb3cql/Panda-v0/noisy300-delta-v0 --labels clean

A 3 x 256 MLP regresses z-scored actions on z-scored observations (mean squared error, Adam 1e-3, batch 256), then
acts deterministically in the dataset's own env (``recover_environment``: same task and action mode) on held-out
seeds. ``--labels clean`` learns the controller's actions before noise (``infos["clean_action"]`` of a noisy
dataset), ``executed`` the dataset's actions.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th
from torch import nn

import envs  # noqa: F401  (registers the tasks)
from sb3_cql.data import load_dataset


def dataset_arrays(dataset_id: str, labels: str) -> tuple[np.ndarray, np.ndarray]:
    """Observations and actions (clean or executed) of every transition."""
    observations, actions = [], []
    for episode in load_dataset(dataset_id).iterate_episodes():
        if labels == "clean" and "clean_action" not in episode.infos:
            raise ValueError(f"{dataset_id} has no clean actions (not a noisy dataset): use --labels executed")
        observations.append(episode.observations[:-1])
        actions.append(episode.infos["clean_action"][: len(episode.actions)] if labels == "clean" else episode.actions)
    return np.concatenate(observations).astype(np.float32), np.concatenate(actions).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset-id", required=True)
    parser.add_argument("--labels", choices=["clean", "executed"], default="executed")
    parser.add_argument("--steps", type=int, default=4000, help="gradient steps")
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--eval-seed", type=int, default=1000, help="first evaluation seed (held out from the data)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.manual_seed(args.seed)

    observations, actions = dataset_arrays(args.dataset_id, args.labels)
    observation_mean, observation_std = observations.mean(axis=0), observations.std(axis=0) + 1e-6
    action_mean, action_std = actions.mean(axis=0), actions.std(axis=0) + 1e-6
    inputs = th.as_tensor((observations - observation_mean) / observation_std)
    targets = th.as_tensor((actions - action_mean) / action_std)
    network = nn.Sequential(nn.Linear(inputs.shape[1], 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                            nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, targets.shape[1]))  # fmt: skip
    optimizer = th.optim.Adam(network.parameters(), lr=1e-3)
    start = time.perf_counter()
    for _ in range(args.steps):
        batch = th.randint(0, len(inputs), (256,))
        loss = (network(inputs[batch]) - targets[batch]).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    print(f"{args.dataset_id}, {args.labels} actions: {len(inputs)} transitions, {args.steps} steps in "
          f"{time.perf_counter() - start:.0f} s, final loss {loss.item():.4f}")  # fmt: skip

    env = load_dataset(args.dataset_id).recover_environment()
    successes = []
    for seed in range(args.eval_seed, args.eval_seed + args.eval_episodes):
        observation, _ = env.reset(seed=seed)
        terminated = truncated = False
        while not (terminated or truncated):
            with th.no_grad():
                z = network(th.as_tensor((observation - observation_mean) / observation_std)[None])[0].numpy()
            action = np.clip(z * action_std + action_mean, env.action_space.low, env.action_space.high)
            observation, _, terminated, truncated, info = env.step(action)
        successes.append(info["is_success"])
    print(f"success rate {np.mean(successes):.2f} over {args.eval_episodes} episodes "
          f"(seeds {args.eval_seed}-{args.eval_seed + args.eval_episodes - 1})")  # fmt: skip
    env.close()


if __name__ == "__main__":
    main()
