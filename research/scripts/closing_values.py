"""What a trained critic makes of the hand's yaw on a knocked-out cylinder, read off a dataset's own episodes.

Usage: python research/scripts/closing_values.py MODEL.zip [--algo cql] [--dataset ID] [--episodes N] [--segment N]
[--threads N]

Two readings, both at states of the dataset's episodes (its first ``--episodes``) where the cylinder lies on its side:

- **At the closings** (``envs.pd_controller.closing_steps``): by the angle between the fingers' closing direction and
  the cylinder's axis (90: across it), how often the closing lifted the cylinder (a success before the next
  closing), the discounted return the data earned from there (``sb3_cql.common.returns_to_go`` with the model's
  ``reward_scale``, ``reward_bias`` and ``gamma``: a failed episode cut at 700 steps sits at the floor
  ``reward_bias / (1 - gamma)``), and the critics' value of the data's action (chunk) there (the twin critics'
  minimum, in the same units). A critic that sees the payoff of a turned hand ranks the closings as the returns do.
- **At the same state, turned either way**: at the states where the open hand hovers above the lying cylinder (the
  point between the fingers within 3 cm of it horizontally, 5 to 25 cm above it; every 10th such step) more than 20
  degrees from a yaw that grasps it, the policy's own deterministic action (chunk) with the wrist joint's delta set
  to +1 in every action of the chunk, and to -1: towards that yaw and away from it (which sign turns which way is
  read off the data). Printed: the critic's value of the first minus that of the second, and how often the
  policy's own first wrist action turns towards the grasping yaw. Then the data's own actions at those states: the
  critic's advantage (IQL's ``Q - V``; the value for a model without a value network) of those whose first wrist
  action turns towards the grasping yaw minus those that turn away, the signal an advantage-weighted actor learns.
  ``V(s)`` is IQL's value network, else the critics' value of the policy's own action. Last, the data's segments of
  ``--segment`` steps from those states: their advantage (discounted return plus the discounted ``V`` at their end,
  minus ``V(s)``) for those that end nearer a grasping yaw minus those that end farther, and the rank correlation of
  ``V(s)`` with the turn still needed (negative where a hand nearer a grasping yaw is worth more).

Printed::

    MODEL (action_chunk 1) on DATASET, 1000 episodes: 620 closings on a lying cylinder
    angle (deg)  closings  lifted  data's return  critic's value
        0-30         70    0.01         -197.1          -430.2
    ...
    rank correlation over the closings: critic's value vs lifted 0.12, vs data's return 0.10, vs angle 0.02; data's
    return vs angle 0.05
    1385 hovering states more than 20 deg from a grasping yaw: value turned towards it minus away from it +0.01 ...
    the data's own actions there: advantage of those that turn towards it minus away +0.002 (690 towards, 695 away)
    the data's 25-step segments from there: advantage of those that end nearer a grasping yaw minus farther +0.007 ...

The model must act in delta actions (``action_mode: delta``), whose wrist component turns the hand. Nothing is
written; torch runs ``--threads`` threads (1 by default).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np
import torch as th
from _cli import positive_int
from rl_zoo3 import ALGOS
from scipy import stats

import envs
import sb3_cql  # noqa: F401  (registers cql, bc and iql with the zoo)
from envs.pd_controller import GRIPPER_OPEN_WIDTH, aligned_yaw, closing_angle, closing_steps, hand_yaw
from sb3_cql.common import returns_to_go
from sb3_cql.data import DatasetError, load_dataset

WRIST = 6  # index of the wrist joint (panda_joint7) in the 9-D joint action
ANGLE_GROUPS = ((0, 30), (30, 60), (60, 90))
TURN_NEEDED = np.radians(20)
HOVER_XY, HOVER_HEIGHTS, HOVER_EVERY = 0.03, (0.05, 0.25), 10
SLICES = envs.OBSERVATION_SLICES


def values(model: Any, observations: np.ndarray, chunks: np.ndarray) -> np.ndarray:
    """The twin critics' minimum value of each observation with its flattened action chunk (as values: an IQL's
    success-scale logits through their sigmoid)."""
    with th.no_grad():
        obs = th.as_tensor(observations, dtype=th.float32, device=model.device)
        act = th.as_tensor(chunks, dtype=th.float32, device=model.device)
        return as_values(model, th.cat(model.critic(obs, act), dim=1)).min(dim=1).values.cpu().numpy()


def as_values(model: Any, outputs: th.Tensor) -> th.Tensor:
    """A network's ``outputs`` as values: an IQL's (``IQL.as_values``, the sigmoid of success-scale logits), else
    themselves."""
    return model.as_values(outputs) if hasattr(model, "as_values") else outputs


def policy_chunks(model: Any, observations: np.ndarray) -> np.ndarray:
    """The deterministic policy's action chunks (flattened) at ``observations``."""
    with th.no_grad():
        obs = th.as_tensor(observations, dtype=th.float32, device=model.device)
        return model.actor(obs, deterministic=True).cpu().numpy()


def turn_to_grasp(observation: np.ndarray) -> float:
    """The turn (rad, in [-pi/2, pi/2)) of the hand's yaw to the nearer yaw that grasps the lying cylinder."""
    target = aligned_yaw(observation[SLICES["object_orientation"]])
    return float((target - hand_yaw(observation[SLICES["ee_orientation"]]) + np.pi / 2) % np.pi - np.pi / 2)


def hovering_steps(observations: np.ndarray) -> np.ndarray:
    """Every ``HOVER_EVERY``-th step at which the open hand hovers above the object (see the module's docstring)."""
    offsets = observations[:, SLICES["finger_offsets"]].reshape(len(observations), 2, 3).mean(axis=1)
    widths = observations[:, SLICES["joint_positions"]][:, -2:].sum(axis=1)
    hovering = (
        (np.linalg.norm(offsets[:, :2], axis=1) < HOVER_XY)
        & (offsets[:, 2] > HOVER_HEIGHTS[0])
        & (offsets[:, 2] < HOVER_HEIGHTS[1])
        & (widths >= GRIPPER_OPEN_WIDTH - 0.005)
    )
    return np.flatnonzero(hovering)[::HOVER_EVERY]


def wrist_turn_sign(episodes: list[Any]) -> float:
    """+1 if a positive wrist delta turns the hand's yaw up in the data, -1 if down."""
    actions, turns = [], []
    for episode in episodes:
        yaws = np.array([hand_yaw(o[SLICES["ee_orientation"]]) for o in episode.observations])
        turns.append((np.diff(yaws) + np.pi) % (2 * np.pi) - np.pi)
        actions.append(episode.actions[:, WRIST])
    return float(np.sign(np.corrcoef(np.concatenate(actions), np.concatenate(turns))[0, 1]))


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation (scipy's; nan for fewer than two values or a constant one)."""
    if len(a) < 2 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(stats.spearmanr(a, b).statistic)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/closing_values.py", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("model", help="a saved model with critics, trained in delta actions (.zip)")
    parser.add_argument("--algo", default="cql", choices=sorted(ALGOS), help="its RL-Zoo3 name (cql)")
    parser.add_argument("--dataset", default="sb3cql/PandaForce-v0/noisy-regrasp-yaw-delta-1k-v0", help="dataset id")
    parser.add_argument("--episodes", type=positive_int, default=1000, help="the dataset's first N episodes (1000)")
    parser.add_argument("--segment", type=positive_int, default=25, help="steps of the data's segments (25)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = ALGOS[args.algo].load(args.model, device="cpu")
        dataset = load_dataset(args.dataset)
    except (ValueError, OSError, DatasetError) as error:
        sys.exit(f"error: {error}")
    space = model.action_space
    if space.shape != (9,) or not (np.all(space.low == -1) and np.all(space.high == 1)):
        sys.exit(f"error: {args.model} does not act in delta actions (its action space: {space})")
    h = getattr(model.policy, "action_chunk", 1)
    scale, bias = getattr(model, "reward_scale", 1.0), getattr(model, "reward_bias", 0.0)
    episodes = list(dataset.iterate_episodes(range(min(args.episodes, dataset.total_episodes))))

    closings: list[tuple[float, bool, float, np.ndarray, np.ndarray]] = []  # angle, lifted, return, obs, chunk
    hovers: list[tuple[np.ndarray, float, np.ndarray | None, Segment | None]] = []  # obs, turn, data's chunk, segment
    for episode in episodes:
        observations, actions = episode.observations[:-1], episode.actions
        returns = returns_to_go(scale * episode.rewards + bias, bool(episode.truncations[-1]), model.gamma)
        lifts = np.flatnonzero(episode.rewards > 0)
        steps = closing_steps(observations)
        for step, next_closing in zip(steps, [*steps[1:], len(actions)], strict=False):  # none without a closing
            angle = closing_angle(observations[step])
            if angle is not None and step + h <= len(actions):
                lifted = bool(np.any((lifts >= step) & (lifts < next_closing)))
                closings.append((angle, lifted, returns[step], observations[step], actions[step : step + h].ravel()))
        for step in hovering_steps(observations):
            turn = turn_to_grasp(observations[step])
            if closing_angle(observations[step]) is not None and abs(turn) > TURN_NEEDED:
                chunk = actions[step : step + h].ravel() if step + h <= len(actions) else None
                data = segment(episode, step, args.segment, scale, bias, model.gamma)
                hovers.append((observations[step], turn, chunk, data))

    print(f"{args.model} (action_chunk {h}) on {args.dataset}, {len(episodes)} episodes: "
          f"{len(closings)} closings on a lying cylinder")  # fmt: skip
    if closings:
        angles, lifted, returns = (np.array([closing[i] for closing in closings]) for i in range(3))
        q = values(model, np.stack([c[3] for c in closings]), np.stack([c[4] for c in closings]))
        print("angle (deg)  closings  lifted  data's return  critic's value")
        for low, high in ANGLE_GROUPS:
            group = (angles >= low) & ((angles < high) if high < 90 else (angles <= high))
            if group.any():
                print(f"{low:>6}-{high:<4} {group.sum():>9} {lifted[group].mean():>7.2f} {returns[group].mean():>14.1f} "
                      f"{q[group].mean():>15.1f}")  # fmt: skip
            else:
                print(f"{low:>6}-{high:<4} {0:>9}       -              -               -")
        print(f"rank correlation over the closings: critic's value vs lifted {spearman(q, lifted.astype(float)):.2f}, "
              f"vs data's return {spearman(q, returns):.2f}, vs angle {spearman(q, angles):.2f}; data's return vs angle "
              f"{spearman(returns, angles):.2f}")  # fmt: skip
    if not hovers:
        print("no hovering states more than 20 deg from a grasping yaw")
        return
    observations = np.stack([hover[0] for hover in hovers])
    towards = np.sign([hover[1] for hover in hovers]) * wrist_turn_sign(episodes)  # the wrist delta's sign that turns towards
    own = policy_chunks(model, observations).reshape(len(hovers), h, -1)
    turned = {}
    for name, sign in (("towards", towards), ("away", -towards)):
        chunk = own.copy()
        chunk[:, :, WRIST] = sign[:, None]
        turned[name] = values(model, observations, chunk.reshape(len(hovers), -1))
    difference = turned["towards"] - turned["away"]
    print(
        f"{len(hovers)} hovering states more than 20 deg from a grasping yaw: value turned towards it minus away from "
        f"it {difference.mean():+.2f} (std {difference.std():.2f}, positive at {np.mean(difference > 0):.2f} of the "
        f"states); the policy's own wrist action turns towards it at {np.mean(np.sign(own[:, 0, WRIST]) == towards):.2f}"
    )
    state_value = state_values(model, observations)
    print(data_actions_line(model, hovers, state_value, towards, h))
    print(segments_line(model, hovers, state_value, args.segment))


def state_values(model: Any, observations: np.ndarray) -> np.ndarray:
    """``V(s)``: a value network's (IQL's, as values), else the critics' value of the policy's own action (chunk)."""
    if not hasattr(model, "value_net"):
        return values(model, observations, policy_chunks(model, observations))
    with th.no_grad():
        outputs = model.value_net(th.as_tensor(observations, dtype=th.float32, device=model.device))
        return as_values(model, outputs).flatten().cpu().numpy()


def data_actions_line(model: Any, hovers: list[Any], state_value: np.ndarray, towards: np.ndarray, h: int) -> str:
    """At the hovering states, how the critic scores the data's own actions (chunks) by the way their first wrist
    action turns: the advantage ``Q(s, a) - V(s)`` (``state_value``, :func:`state_values` of the states) of those that
    turn towards a grasping yaw minus those that turn away. What an advantage-weighted actor learns from."""
    kept = [i for i, hover in enumerate(hovers) if hover[2] is not None]
    observations = np.stack([hovers[i][0] for i in kept])
    chunks = np.stack([hovers[i][2] for i in kept])
    advantages = values(model, observations, chunks) - state_value[kept]
    turning = np.sign(chunks.reshape(len(kept), h, -1)[:, 0, WRIST]) == towards[kept]
    if turning.all() or not turning.any():
        return f"the data's own actions there: all {len(kept)} turn {'towards' if turning.all() else 'away'}"
    return (
        f"the data's own actions there: advantage of those that turn towards it minus away "
        f"{advantages[turning].mean() - advantages[~turning].mean():+.3f} ({turning.sum()} towards, {(~turning).sum()} away)"
    )


Segment = tuple[np.ndarray, float, float, float]  # last observation, discounted return, bootstrap discount, turn gained


def segment(episode: Any, step: int, length: int, scale: float, bias: float, gamma: float) -> Segment | None:
    """The data's ``length`` steps from ``step`` (fewer at the episode's end): the observation they end at, their
    discounted rewards ``scale * r + bias``, the discount on the value there (0 after a termination) and how much
    nearer a grasping yaw they brought the hand (rad); ``None`` if the cylinder no longer lies at the end."""
    end = min(step + length, len(episode.actions))
    last = episode.observations[end]
    if closing_angle(last) is None:
        return None
    rewards = scale * episode.rewards[step:end] + bias
    discounted = float(np.sum(rewards * gamma ** np.arange(end - step)))
    bootstrap = 0.0 if episode.terminations[end - 1] else gamma ** (end - step)
    gained = abs(turn_to_grasp(episode.observations[step])) - abs(turn_to_grasp(last))
    return last, discounted, bootstrap, gained


def segments_line(model: Any, hovers: list[Any], state_value: np.ndarray, length: int) -> str:
    """At the hovering states, the data's segments of ``length`` steps: their advantage ``return + discount * V(end) -
    V(s)`` (``state_value``, :func:`state_values` of the states), those that end nearer a grasping yaw minus those that
    end farther, and the rank correlation of ``V(s)`` with the turn the hand still needs there (negative: a hand nearer
    a grasping yaw is worth more)."""
    correlation = spearman(state_value, np.abs([hover[1] for hover in hovers]))
    kept = [i for i, hover in enumerate(hovers) if hover[3] is not None]
    if not kept:
        return (f"{length}-step segments: none ends on a lying cylinder; rank correlation of V with the turn still "
                f"needed {correlation:.2f}")  # fmt: skip
    ends = state_values(model, np.stack([hovers[i][3][0] for i in kept]))
    returns, bootstraps, gained = (np.array([hovers[i][3][j] for i in kept]) for j in (1, 2, 3))
    advantages = returns + bootstraps * ends - state_value[kept]
    nearer = gained > 0
    difference = advantages[nearer].mean() - advantages[~nearer].mean() if nearer.any() and (~nearer).any() else 0.0
    return (
        f"the data's {length}-step segments from there: advantage of those that end nearer a grasping yaw minus farther "
        f"{difference:+.3f} (std {advantages.std():.3f}; {nearer.sum()} nearer, {(~nearer).sum()} farther); rank "
        f"correlation of V with the turn still needed {correlation:.2f}"
    )


if __name__ == "__main__":
    main()
