"""What a trained critic makes of the hand's yaw on a knocked-out cylinder, read off a dataset's own episodes.

    python benchmarks/closing_values.py MODEL.zip --algo cql
    python benchmarks/closing_values.py MODEL.zip --algo cql --dataset sb3cql/PandaForce-v0/noisy-regrasp-yaw-delta-1k-v0

Two readings, both at states of the dataset's episodes where the cylinder lies on its side:

- **At the closings** (``envs.pd_controller.closing_steps``): by the angle between the fingers' closing direction and
  the cylinder's axis (90: across it), how often the data lifted the cylinder before the next closing, the discounted
  return the data earned from there (with the model's ``reward_scale``, ``reward_bias`` and ``gamma``), and the
  critics' value of the data's action (chunk) there (the smaller of the twin critics, in the same units). A critic
  that sees the payoff of a turned hand ranks the closings as the returns do.
- **At the same state, turned either way**: at the states where the open hand hovers above the lying cylinder
  (finger midpoint within 3 cm of it horizontally, 5 to 25 cm above it) and is more than 20 degrees from a yaw that
  grasps it, the policy's own action (chunk) with the wrist joint's delta set to +1 or -1 in every action of the
  chunk: towards the grasping yaw or away from it. The critic's value of the first minus that of the second, and how
  often the policy's own wrist action turns towards it.

The model must be trained in delta actions (``action_mode: delta``), whose wrist component turns the hand.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch as th
from rl_zoo3 import ALGOS

import envs
import sb3_cql  # noqa: F401  (registers cql and bc with the zoo)
from envs.pd_controller import aligned_yaw, closing_angle, closing_steps, hand_yaw
from sb3_cql.data import load_dataset

WRIST = 6  # index of the wrist joint (panda_joint7) in the 9-D joint action
ANGLE_GROUPS = ((0, 30), (30, 60), (60, 90.01))
TURN_NEEDED = np.radians(20)


def values(model, observations: np.ndarray, chunks: np.ndarray) -> np.ndarray:
    """The smaller twin critic's value of each observation with its flattened action chunk."""
    with th.no_grad():
        obs = th.as_tensor(observations, dtype=th.float32, device=model.device)
        act = th.as_tensor(chunks, dtype=th.float32, device=model.device)
        return th.cat(model.critic(obs, act), dim=1).min(dim=1).values.cpu().numpy()


def policy_chunks(model, observations: np.ndarray) -> np.ndarray:
    """The deterministic policy's action chunks (flattened, scaled) at ``observations``."""
    with th.no_grad():
        obs = th.as_tensor(observations, dtype=th.float32, device=model.device)
        return model.actor(obs, deterministic=True).cpu().numpy()


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    returns, running = np.zeros(len(rewards)), 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        returns[t] = running
    return returns


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model")
    parser.add_argument("--algo", default="cql")
    parser.add_argument("--dataset", default="sb3cql/PandaForce-v0/noisy-regrasp-yaw-delta-1k-v0")
    parser.add_argument("--episodes", type=int, default=1000, help="the dataset's first N episodes (default 1000)")
    args = parser.parse_args(argv)
    model = ALGOS[args.algo].load(args.model, device="cpu")
    if not np.allclose(model.action_space.low, -1) or model.action_space.shape[-1] != 9:
        sys.exit(f"{args.model}: not a model of delta actions (action space {model.action_space})")
    h = getattr(model.policy, "action_chunk", 1)
    scale, bias = getattr(model, "reward_scale", 1.0), getattr(model, "reward_bias", 0.0)
    dataset = load_dataset(args.dataset)

    closings, hovers = [], []  # (angle, lifted, return, observation, chunk); (observation, towards sign)
    for episode in dataset.iterate_episodes(range(min(args.episodes, dataset.total_episodes))):
        observations, actions = episode.observations, episode.actions
        returns = discounted_returns(scale * episode.rewards + bias, model.gamma)
        lifted = np.flatnonzero(episode.rewards > 0)
        steps = closing_steps(observations[:-1])
        for t, next_closing in zip(steps, [*steps[1:], len(actions)], strict=False):  # none if no closing
            angle = closing_angle(observations[t])
            if angle is None or t + h > len(actions):
                continue
            lift = bool(np.any((lifted >= t) & (lifted < next_closing)))  # the lift that this closing made
            closings.append((angle, lift, returns[t], observations[t], actions[t : t + h].ravel()))
        offsets = observations[:-1, envs.OBSERVATION_SLICES["finger_offsets"]].reshape(-1, 2, 3).mean(axis=1)
        widths = observations[:-1, envs.OBSERVATION_SLICES["joint_positions"]][:, -2:].sum(axis=1)
        candidates = np.flatnonzero(
            (np.linalg.norm(offsets[:, :2], axis=1) < 0.03)
            & (offsets[:, 2] > 0.05)
            & (offsets[:, 2] < 0.25)
            & (widths >= envs.pd_controller.GRIPPER_OPEN_WIDTH - 0.005)
        )
        for t in candidates[::10]:  # every 10th: the hovers of an attempt are alike
            observation = observations[t]
            if closing_angle(observation) is None:
                continue
            target = aligned_yaw(observation[envs.OBSERVATION_SLICES["object_orientation"]])
            error = (target - hand_yaw(observation[envs.OBSERVATION_SLICES["ee_orientation"]]) + np.pi / 2) % np.pi
            error -= np.pi / 2  # the turn (rad) to the nearer grasping yaw, in [-pi/2, pi/2)
            if abs(error) > TURN_NEEDED:
                hovers.append((observation, np.sign(error)))

    print(f"{args.model} (h = {h}) on {args.dataset}: {len(closings)} closings on a lying cylinder")
    print("angle (deg)  closings  lifted before the next closing  data's return  critic's value")
    angles = np.array([c[0] for c in closings])
    q = values(model, np.stack([c[3] for c in closings]), np.stack([c[4] for c in closings]))
    lifts, rets = np.array([c[1] for c in closings]), np.array([c[2] for c in closings])
    for low, high in ANGLE_GROUPS:
        mask = (angles >= low) & (angles < high)
        print(
            f"{low:>4.0f}-{min(high, 90):<4.0f}     {mask.sum():>5}  {lifts[mask].mean():>30.2f}  "
            f"{rets[mask].mean():>13.1f}  {q[mask].mean():>14.1f}"
        )
    print(
        f"rank correlation over the closings: critic's value vs data's return {spearman(q, rets):.2f}, "
        f"vs angle {spearman(q, angles):.2f}; data's return vs angle {spearman(rets, angles):.2f}"
    )

    # The sign of the yaw change that a positive wrist delta gives, from the data themselves.
    episode = next(dataset.iterate_episodes([0]))
    yaws = np.array([hand_yaw(o[envs.OBSERVATION_SLICES["ee_orientation"]]) for o in episode.observations])
    turns = (np.diff(yaws) + np.pi) % (2 * np.pi) - np.pi
    wrist_sign = np.sign(np.corrcoef(episode.actions[:, WRIST], turns)[0, 1])
    observations = np.stack([o for o, _ in hovers])
    towards = np.array([s for _, s in hovers]) * wrist_sign  # the wrist delta's sign that turns towards a grasp
    own = policy_chunks(model, observations).reshape(len(hovers), h, -1)
    turned = {}
    for name, sign in (("towards", towards), ("away", -towards)):
        chunk = own.copy()
        chunk[:, :, WRIST] = sign[:, None]
        turned[name] = values(model, observations, chunk.reshape(len(hovers), -1))
    difference = turned["towards"] - turned["away"]
    own_towards = np.mean(np.sign(own[:, 0, WRIST]) == towards)
    print(
        f"{len(hovers)} hovering states more than 20 deg from a grasping yaw: value of the chunk turned towards it "
        f"minus away from it {difference.mean():+.2f} (std {difference.std():.2f}; positive at "
        f"{np.mean(difference > 0):.2f} of the states); the policy's own wrist action turns towards it at "
        f"{own_towards:.2f} of them"
    )


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    ranks = lambda x: np.argsort(np.argsort(x))  # noqa: E731
    return float(np.corrcoef(ranks(a), ranks(b))[0, 1])


if __name__ == "__main__":
    main()
