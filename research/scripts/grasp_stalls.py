"""Where a policy whose episodes fail without ever closing the hand stops, and what the data and its critics say there.

Usage: python research/scripts/grasp_stalls.py MODEL.zip [--algo iql] [--env Panda-v0] [--seeds 60000-60049]
[--dataset ID] [--episodes N] [--threads N]

Two readings:

- **The data**: at the steps of the dataset's first ``--episodes`` episodes where the open hand is over an upright
  cylinder, by the PD controller's alignment error (the largest of the end effector's offsets from the object's
  centre along x, y and z; the controller closes within ``GRASP_XY_TOLERANCE`` and ``GRASP_Z_TOLERANCE``, 1 cm), how
  many steps there are and the share of them whose gripper command closes (in delta actions the fingers' commands
  are +1 open, -1 close). A controller that closes as soon as it is aligned leaves few steps inside the tolerance.
- **The policy**: the episodes reset with ``--seeds`` played with the deterministic action in the action mode the
  model was trained in. A *stall* is a failed episode in which the fingers never began to close on the object
  (:func:`envs.pd_controller.closing_steps`). For the stalls, at their last step: the alignment error, the policy's
  gripper command (the mean of the fingers' two), and for a model with critics the twin critics' minimum value of
  its own action minus that of the same action with both fingers' commands at -1 (closing); positive where the
  critics prefer the hand to stay open.

Printed::

    sb3cql/PandaForce-v0/noisy-regrasp-yaw-delta-1k-v0, 300 episodes: open hand over an upright cylinder by alignment error
      0-1 cm: 234 steps, 1.00 close
      1-1.5 cm: 785 steps, 0.00 close
      ...
    MODEL on Panda-v0, 50 episodes (seeds 60000-60049): success 0.42, 23 stalls
      stalls at their last step: alignment error 1.7 cm (median; 1.0-2.5), gripper command +0.55 (mean; +0.06 to
      +0.98), critics' value of their action minus closing +0.022 (mean; positive at 21 of 23)

Use seeds outside the protocol's evaluation seeds (117, 12321, 7456, 3426, 573) and outside those of the evaluations
the findings compare with; nothing is written. Torch runs ``--threads`` threads (1 by default).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from _cli import positive_int
from closing_values import values

import envs
import sb3_cql  # noqa: F401  (registers cql, bc and iql with the zoo)
from envs.pd_controller import GRIPPER_OPEN_WIDTH, closing_angle, closing_steps
from sb3_cql.data import DatasetError, load_dataset
from sb3_cql.data.spaces import env_kwargs_for
from sb3_cql.evaluate import load_policy, parse_seeds

SLICES = envs.OBSERVATION_SLICES
#: The bands of the alignment error (m) the data's steps are counted in.
BANDS = ((0.0, 0.01), (0.01, 0.015), (0.015, 0.025), (0.025, 0.04))
FINGERS = slice(-2, None)  # the fingers' two commands, the last of the 9-D joint action


def alignment_errors(observations: np.ndarray) -> np.ndarray:
    """The PD controller's alignment error (m) at each observation: the largest of the end effector's offsets from the
    object's centre (its grasp point) along x, y and z."""
    offsets = observations[:, SLICES["object_position"]] - observations[:, SLICES["ee_position"]]
    return np.abs(offsets).max(axis=1)


def open_over_upright(observations: np.ndarray) -> np.ndarray:
    """Whether, at each observation, the fingers are open over an upright cylinder."""
    widths = observations[:, SLICES["joint_positions"]][:, FINGERS].sum(axis=1)
    upright = np.array([closing_angle(observation) is None for observation in observations])
    return (widths >= GRIPPER_OPEN_WIDTH - 0.005) & upright


def data_lines(dataset_id: str, episodes: int) -> list[str]:
    """The data's reading (the module's docstring)."""
    dataset = load_dataset(dataset_id)
    errors, closes = [], []
    for episode in dataset.iterate_episodes(range(min(episodes, dataset.total_episodes))):
        observations = np.asarray(episode.observations[:-1], dtype=np.float64)
        kept = open_over_upright(observations)
        errors.append(alignment_errors(observations)[kept])
        closes.append(episode.actions[kept][:, FINGERS].mean(axis=1) < 0)
    error, close = np.concatenate(errors), np.concatenate(closes)
    lines = [f"{dataset_id}, {min(episodes, dataset.total_episodes)} episodes: open hand over an upright cylinder by "
             "alignment error"]  # fmt: skip
    for low, high in BANDS:
        band = (error >= low) & (error < high)
        share = f"{close[band].mean():.2f}" if band.any() else "-"
        lines.append(f"  {low * 100:g}-{high * 100:g} cm: {band.sum()} steps, {share} close")
    return lines


def critic_gap(model: Any, observation: np.ndarray, action: np.ndarray) -> float | None:
    """The twin critics' minimum value of ``action`` minus that of ``action`` with the fingers closing; ``None`` for a
    model without critics or acting in chunks."""
    if not hasattr(model, "critic") or getattr(model.policy, "action_chunk", 1) != 1:
        return None
    closing = action.copy()
    closing[FINGERS] = -1.0
    own, closed = values(model, np.stack([observation, observation]), np.stack([action, closing]))
    return float(own - closed)


def play(model: Any, env_id: str, seeds: range) -> tuple[int, list[tuple[float, float, float | None]]]:
    """The successes over the episodes of ``seeds``, and each stall's alignment error, gripper command and critics'
    gap at its last step."""
    env = gym.make(env_id, **env_kwargs_for(model, env_id))
    successes, stalls = 0, []
    try:
        for seed in seeds:
            observation, info = env.reset(seed=int(seed))
            observations, done = [observation], False
            while not done:
                action, _ = model.predict(observation, deterministic=True)
                last = (observation, np.asarray(action, dtype=np.float32))
                observation, _, terminated, truncated, info = env.step(action)
                observations.append(observation)
                done = terminated or truncated
            success = bool(info.get("is_success", False))
            successes += success
            if not success and closing_steps(np.array(observations)).size == 0:
                error = alignment_errors(np.asarray(last[0], dtype=np.float64)[None])[0]
                stalls.append((float(error), float(last[1][FINGERS].mean()), critic_gap(model, *last)))
    finally:
        env.close()
    return successes, stalls


def stalls_line(stalls: list[tuple[float, float, float | None]]) -> str:
    """The stalls' summary (the module's docstring)."""
    error = np.array([stall[0] for stall in stalls]) * 100
    command = np.array([stall[1] for stall in stalls])
    line = (f"  stalls at their last step: alignment error {np.median(error):.1f} cm (median; {error.min():.1f}-"
            f"{error.max():.1f}), gripper command {command.mean():+.2f} (mean; {command.min():+.2f} to "
            f"{command.max():+.2f})")  # fmt: skip
    gaps = np.array([stall[2] for stall in stalls if stall[2] is not None])
    if gaps.size:
        line += (f", critics' value of their action minus closing {gaps.mean():+.3f} (mean; positive at "
                 f"{(gaps > 0).sum()} of {gaps.size})")  # fmt: skip
    return line


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/grasp_stalls.py", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("model", help="a saved model trained in delta actions (.zip)")
    parser.add_argument("--algo", default="iql", help="its RL-Zoo3 name (iql)")
    parser.add_argument("--env", default="Panda-v0", choices=list(envs.ENV_IDS), help="the task played (Panda-v0)")
    parser.add_argument("--seeds", type=parse_seeds, default=range(60000, 60050), help="episode seeds (60000-60049)")
    parser.add_argument("--dataset", default="sb3cql/PandaForce-v0/noisy-regrasp-yaw-delta-1k-v0", help="dataset id")
    parser.add_argument("--episodes", type=positive_int, default=300, help="the dataset's first N episodes (300)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = load_policy(args.model, args.algo, args.env)
        lines = data_lines(args.dataset, args.episodes)
        successes, stalls = play(model, args.env, args.seeds)
    except (ValueError, OSError, DatasetError) as error:
        sys.exit(f"error: {error}")
    print("\n".join(lines))
    episodes = len(args.seeds)
    print(f"{args.model} on {args.env}, {episodes} episodes (seeds {args.seeds.start}-{args.seeds.stop - 1}): success "
          f"{successes / episodes:.2f}, {len(stalls)} stalls")  # fmt: skip
    if stalls:
        print(stalls_line(stalls))


if __name__ == "__main__":
    main()
