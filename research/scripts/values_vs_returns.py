"""A fine-tuned CQL model's values against the returns its data actually earned: online and offline states, of
successful and failed episodes.

Usage: python research/scripts/values_vs_returns.py MODEL.zip BUFFER.pkl [--offline-states N] [--seed S] [--threads N]

``MODEL.zip`` is a :class:`sb3_cql.CQL` model fine-tuned online (one action a state, or in action chunks: then
``a`` is the stored chunk from each state) and ``BUFFER.pkl`` the online transitions saved with
it (``save_replay_buffer``, or a fine-tuning checkpoint's ``rl_model_replay_buffer_<N>_steps.pkl``); its offline data
come back from the model's dataset id (collected first if missing, as the model does). Every state of an ended
online episode and ``--offline-states`` (5000) states drawn from the offline data (``--seed``, 0) are scored with the
twin critics' minimum Q at the stored action, ``Q(s,a)``, and at the policy's deterministic action, ``Q(s,pi)``,
beside the state's discounted return-to-go under the critics' reward transform (:func:`sb3_cql.common.returns_to_go`:
a failed episode cut at 700 steps earns the per-step reward forever, the floor ``reward_bias / (1 - gamma)``). An
episode is successful when its return-to-go lies above that floor. Printed::

    online: 31 episodes ended (10 successful), 19999 transitions; 18 of the 21 failed ones reopen the gripper
    group                states     RTG  Q(s,a) Q(s,pi) Q(s,pi)<RTG  corr(Q(s,a),RTG) median Q(s,a) Q(s,a)<RTG-100
    online successful      4629  -157.2  -166.4  -164.7       0.541              0.92        -189.6          0.000
    online failed         14700  -200.0  -421.6  -419.9       0.163               nan        -196.1          0.044
    ...
    online successful, steps before the end: 0-99: RTG -71.9, median Q(s,a) -79.6 (1000); 100-199: ...

(Q columns are means unless named.) ``Q(s,pi)<RTG`` is the fraction of states whose policy value lies below what
the data's episode earned from there (where calibrated CQL's bound lifts the pushed-down value); the correlation
says whether the critic ranks states as their outcomes do; ``Q(s,a)<RTG-100`` is the fraction of states valued more
than 100 below their return-to-go. The last line splits the successful online episodes' states by how many steps
before the episode's end (the lift) they lie: with the discount, a success several hundred steps ahead is worth
little more than the floor. A failed episode reopens the gripper when its gripper command (the last action
dimension) opens again after it has first closed (``research/scripts/gripper_reopenings.py``), each held for 20 steps or
more (shorter runs of one sign are the exploration noise's flips). Nothing is written; torch runs ``--threads``
threads (1 by default).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch as th
from _cli import positive_int
from gripper_reopenings import reopens
from stable_baselines3.common.buffers import ReplayBuffer

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL, CalQL
from sb3_cql.common import ActionChunkReplayBuffer, MixedReplayBuffer, ReturnToGoReplayBuffer
from sb3_cql.common.offline import saved_algorithm
from sb3_cql.data import DatasetError

HEADER = (f"{'group':20s} {'states':>6s} {'RTG':>7s} {'Q(s,a)':>7s} {'Q(s,pi)':>7s} {'Q(s,pi)<RTG':>11s} "
          f"{'corr(Q(s,a),RTG)':>17s} {'median Q(s,a)':>13s} {'Q(s,a)<RTG-100':>14s}")  # fmt: skip
#: Steps a gripper command must keep its sign to count (the exploration noise flips single steps).
HELD_STEPS = 20
#: Bins of steps before the end of a successful episode, ``(first, last)``.
BEFORE_SUCCESS = ((0, 99), (100, 199), (200, 399), (400, 699))


def with_returns_to_go(model: CQL, buffer: ReplayBuffer) -> ReturnToGoReplayBuffer:
    """``buffer`` with its returns-to-go under the model's discount and reward transform (as calibrated CQL has them)."""
    if isinstance(buffer, ReturnToGoReplayBuffer):
        return buffer
    return ReturnToGoReplayBuffer.from_replay_buffer(buffer, model.gamma, model.reward_scale, model.reward_bias)


def load_buffers(model: CQL, buffer_path: str) -> tuple[ReturnToGoReplayBuffer, ReturnToGoReplayBuffer]:
    """``(offline data, online transitions)`` of a fine-tuned model, both with returns-to-go."""
    offline = model.load_offline_data()
    model.replay_buffer = None
    model.load_replay_buffer(buffer_path)
    if not isinstance(model.replay_buffer, MixedReplayBuffer):
        kind = type(model.replay_buffer).__name__
        raise ValueError(f"{buffer_path} holds no online transitions of a fine-tuning (a {kind})")
    return with_returns_to_go(model, offline), with_returns_to_go(model, model.replay_buffer.online)


def online_episodes(buffer: ReturnToGoReplayBuffer) -> list[np.ndarray]:
    """Row indices of each ended episode of a buffer filled once from its start (an online part), in order; the
    steps of an episode left unfinished when the fine-tuning resumed from a checkpoint (no return-to-go) are left out."""
    ends = np.flatnonzero(buffer.dones[: buffer.size(), 0] > 0)
    starts = np.concatenate([[0], ends[:-1] + 1]) if len(ends) else np.array([], dtype=np.int64)
    episodes = [np.arange(start, end + 1) for start, end in zip(starts, ends, strict=True)]
    episodes = [rows[np.isfinite(buffer.returns_to_go[rows, 0])] for rows in episodes]
    return [rows for rows in episodes if len(rows)]


def held(commands: np.ndarray, steps: int = HELD_STEPS) -> np.ndarray:
    """The gripper commands less the runs of one sign shorter than ``steps``: what the policy held, not noise flips."""
    runs = np.split(commands, np.flatnonzero(np.diff(np.sign(commands))) + 1)
    kept = [run for run in runs if len(run) >= steps]
    return np.concatenate(kept) if kept else commands[:0]


def stored_actions(model: CQL, buffer: ReturnToGoReplayBuffer, rows: np.ndarray) -> np.ndarray:
    """The stored actions the critics score at ``rows``: each step's, or for a model of action chunks the chunk from
    each step, cut at its episode's end as the model's chunk buffer samples it
    (:meth:`~sb3_cql.common.ActionChunkReplayBuffer.chunk_actions`)."""
    chunk = getattr(model, "action_chunk", 1)
    if chunk == 1:
        return buffer.actions[rows, 0]
    if buffer.n_steps != chunk:
        raise ValueError(f"the buffer reads {buffer.n_steps}-step samples, the model acts in chunks of {chunk}")
    return ActionChunkReplayBuffer.chunk_actions(buffer, rows)  # the chunk buffer's arrays, with its n_steps


def values(model: CQL, buffer: ReturnToGoReplayBuffer, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(returns-to-go, Q(s,a), Q(s,pi))`` of the buffer's ``rows`` (env 0), the twin critics' minimum (``a``: the
    stored action, or chunk: :func:`stored_actions`)."""
    observations = th.as_tensor(buffer.observations[rows, 0], device=model.device)
    actions = th.as_tensor(stored_actions(model, buffer, rows), device=model.device)
    with th.no_grad():
        q_data = th.min(th.cat(model.critic(observations, actions), dim=1), dim=1).values
        policy_actions = model.actor(observations, deterministic=True)
        q_policy = th.min(th.cat(model.critic(observations, policy_actions), dim=1), dim=1).values
    return buffer.returns_to_go[rows, 0].astype(np.float64), q_data.cpu().numpy(), q_policy.cpu().numpy()


def row(name: str, scored: tuple[np.ndarray, np.ndarray, np.ndarray]) -> str:
    returns, q_data, q_policy = scored
    if len(returns) == 0:
        return f"{name:20s} {0:6d}"
    correlation = np.corrcoef(q_data, returns)[0, 1] if len(returns) > 1 and returns.std() > 0 else float("nan")
    return (f"{name:20s} {len(returns):6d} {returns.mean():7.1f} {q_data.mean():7.1f} {q_policy.mean():7.1f} "
            f"{(q_policy < returns).mean():11.3f} {correlation:17.2f} {np.median(q_data):13.1f} "
            f"{(q_data < returns - 100).mean():14.3f}")  # fmt: skip


def before_success(model: CQL, buffer: ReturnToGoReplayBuffer, episodes: list[np.ndarray]) -> str:
    """Mean return-to-go and median Q(s,a) of successful episodes' states by how many steps before the end they lie."""
    parts = []
    for first, last in BEFORE_SUCCESS:
        rows = [rows[::-1][first : last + 1] for rows in episodes]
        rows = np.concatenate(rows) if rows else np.array([], dtype=np.int64)
        if len(rows):
            returns, q_data, _ = values(model, buffer, rows)
            parts.append(f"{first}-{last}: RTG {returns.mean():.1f}, median Q(s,a) {np.median(q_data):.1f} ({len(rows)})")
        else:
            parts.append(f"{first}-{last}: none")
    return "online successful, steps before the end: " + "; ".join(parts)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/values_vs_returns.py", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("model", help="a CQL model fine-tuned online (.zip)")
    parser.add_argument("buffer", help="its online transitions (.pkl)")
    parser.add_argument("--offline-states", type=positive_int, default=5000, help="offline states drawn (5000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of that draw (0)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = {"CalQL": CalQL}.get(saved_algorithm(args.model) or "CQL", CQL).load(args.model)
        offline, online = load_buffers(model, args.buffer)
    except (ValueError, OSError, DatasetError) as error:
        sys.exit(f"error: {error}")
    floor = np.float32(model.reward_bias / (1.0 - model.gamma))  # a failed, cut episode's return-to-go, as stored

    episodes = online_episodes(online)
    successful = [rows for rows in episodes if online.returns_to_go[rows[-1], 0] > floor]
    failed = [rows for rows in episodes if online.returns_to_go[rows[-1], 0] <= floor]
    reopening = sum(reopens(held(online.actions[rows, 0, -1])) for rows in failed)
    print(f"online: {len(episodes)} episodes ended ({len(successful)} successful), {online.size()} transitions; "
          f"{reopening} of the {len(failed)} failed ones reopen the gripper")  # fmt: skip

    rng = np.random.default_rng(args.seed)
    ended = np.flatnonzero(np.isfinite(offline.returns_to_go[: offline.size(), 0]))
    drawn = rng.choice(ended, size=min(args.offline_states, len(ended)), replace=False)
    drawn_success = offline.returns_to_go[drawn, 0] > floor
    empty = np.array([], dtype=np.int64)
    print(HEADER)
    groups = {
        "online successful": np.concatenate(successful) if successful else empty,
        "online failed": np.concatenate(failed) if failed else empty,
        "offline successful": drawn[drawn_success],
        "offline failed": drawn[~drawn_success],
    }
    for name, rows in groups.items():
        print(row(name, values(model, online if name.startswith("online") else offline, rows)), flush=True)
    print(before_success(model, online, successful))


if __name__ == "__main__":
    main()
