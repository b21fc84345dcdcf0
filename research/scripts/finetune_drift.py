"""Where an IQL fine-tuning run's policy leaves its offline start: the actor against its own critics, and what its
exploring episodes do after they close the hand.

Usage: python research/scripts/finetune_drift.py START.zip CHECKPOINT.zip [CHECKPOINT.zip ...] --buffer PKL
[--algo iql] [--states N] [--window N] [--threads N]

``START.zip`` is the offline model, the checkpoints are the run's (``rl_model_<N>_steps.zip``, in order), ``PKL`` a
replay buffer the run saved (``rl_model_replay_buffer_<N>_steps.pkl``: its online transitions, the run's exploring
episodes). ``--algo`` names the class (``iql``, or a research variant's zoo name: ``research/zoo_train.py``). Two
readings:

- **The actor against its critics**, at ``--states`` states drawn from the offline data and as many from the online
  transitions (seed 0), for the start and each checkpoint: the mean absolute change of the deterministic action from
  the start's, for the 7 arm joints and the 2 fingers; the checkpoint's own critics (the twins' minimum) at its action
  minus at the start's action (positive: the actor has climbed its critics away from the start), and its action's
  advantage over its own value network; then, on a batch half offline and half online as fine-tuning draws them, the
  norm of the gradient with respect to the actor's actions of the two parts of the ``ddpg_awr`` loss, the critics'
  normalised value and the anchor (``actor_bc_weight`` times the weighted squared error): the anchor's share is the
  second over their sum.
- **After the closings**, in the offline data's episodes and in the online episodes by ``--window`` env steps
  (10,000; an episode counts in the window it starts in): for the closings on a lying cylinder at 50 to 90 degrees to
  its axis (:func:`envs.pd_controller.closing_angle`), how many, the share that lifted it (a reward before the next
  closing), the share after which the hand was commanded open within 40 steps (the fingers' mean command above 0 for
  20 steps running, ``values_vs_returns.held``: a reopening, not a noise flip), and the mean rise of the hand and of
  the object over those 40 steps.

Prints, and writes nothing::

    checkpoint  |da| arm  |da| fingers  Q(a) - Q(a_start)  Q(a) - V  anchor share
    start       0.000     0.000         +0.0000            ...
    ...
    closings at 50-90 deg  episodes  closings  lifted  reopened  hand rise (cm)  object rise (cm)
    offline data           ...
    online 0-10000         ...
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np
import torch as th
from _cli import positive_int
from stable_baselines3.common.save_util import load_from_pkl
from values_vs_returns import held

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))  # the repository's root, for research/

from envs.panda_env import OBSERVATION_SLICES  # noqa: E402
from envs.pd_controller import closing_angle, closing_steps  # noqa: E402
from research.zoo_train import VARIANTS  # noqa: E402
from sb3_cql import IQL  # noqa: E402
from sb3_cql.common import MixedReplayBuffer  # noqa: E402

#: How many steps after a closing the reopening and the rises are read over.
AFTER = 40
#: Action dimensions: the 7 arm joints, then the two fingers.
ARM, FINGERS = slice(0, 7), slice(7, 9)


def load_class(name: str) -> type[IQL]:
    """``iql`` or the zoo name of a research variant (:data:`research.zoo_train.VARIANTS`)."""
    return IQL if name == "iql" else VARIANTS[name]


def episodes(observations: np.ndarray, actions: np.ndarray, rewards: np.ndarray, ends: np.ndarray):
    """The episodes of a buffer's rows in order, as ``(first row, observations, actions, rewards)``; an unfinished last
    one is left out."""
    start = 0
    for end in np.flatnonzero(ends):
        yield start, observations[start : end + 1], actions[start : end + 1], rewards[start : end + 1]
        start = end + 1


#: The heights (z) of the hand and of the object in an observation.
HAND_Z, OBJECT_Z = OBSERVATION_SLICES["ee_position"].start + 2, OBSERVATION_SLICES["object_position"].start + 2


def closing_outcomes(observations: np.ndarray, actions: np.ndarray, rewards: np.ndarray) -> list[tuple[float, ...]]:
    """``(lifted, reopened, hand rise, object rise)`` (the rises in cm) for each closing of an episode at 50-90
    degrees to a lying cylinder's axis."""
    steps = list(closing_steps(observations))
    outcomes = []
    for index, step in enumerate(steps):
        angle = closing_angle(observations[step])
        if angle is None or angle < 50:
            continue
        stop = steps[index + 1] if index + 1 < len(steps) else len(observations)
        lifted = float((rewards[step:stop] > 0).any())
        after = min(step + AFTER, len(observations) - 1)
        reopened = float((held(actions[step + 1 : after + 1, FINGERS].mean(axis=1)) > 0).any())
        rises = 100 * (observations[after, [HAND_Z, OBJECT_Z]] - observations[step, [HAND_Z, OBJECT_Z]])
        outcomes.append((lifted, reopened, *rises))
    return outcomes


def closing_row(label: str, n_episodes: int, outcomes: list[tuple[float, ...]]) -> str:
    """A row of the closings' table."""
    if not outcomes:
        return f"{label:<22} {n_episodes:>8}  {0:>8}"
    lifted, reopened, hand, thing = (np.asarray(column, dtype=float) for column in zip(*outcomes, strict=True))
    return (f"{label:<22} {n_episodes:>8}  {len(outcomes):>8}  {lifted.mean():>6.2f}  {reopened.mean():>8.2f}  "
            f"{hand.mean():>14.1f}  {thing.mean():>16.1f}")  # fmt: skip


def buffer_rows(buffer) -> tuple[np.ndarray, ...]:
    """A buffer's filled rows (one env): observations, actions, rewards, episode ends."""
    size = buffer.size()
    ends = np.logical_or(buffer.dones[:size, 0], buffer.timeouts[:size, 0])
    return buffer.observations[:size, 0], buffer.actions[:size, 0], buffer.rewards[:size, 0], ends


def probe_states(offline, online, n: int) -> tuple[th.Tensor, th.Tensor]:
    """``n`` states of the offline data and ``n`` of the online transitions (fewer where a part has fewer; seed 0),
    offline first, with the actions stored with them."""
    rng, observations, actions = np.random.default_rng(0), [], []
    for buffer in (offline, online):
        buffer_observations, buffer_actions, _, _ = buffer_rows(buffer)
        rows = rng.choice(len(buffer_observations), min(n, len(buffer_observations)), replace=False)
        observations.append(buffer_observations[rows])
        actions.append(buffer_actions[rows])
    return (th.as_tensor(np.concatenate(observations), dtype=th.float32),
            th.as_tensor(np.concatenate(actions), dtype=th.float32))  # fmt: skip


def deterministic(model: IQL, observations: th.Tensor) -> th.Tensor:
    with th.no_grad():
        return model.policy.acting_actor(observations, deterministic=True)


def twin_min(model: IQL, observations: th.Tensor, actions: th.Tensor) -> th.Tensor:
    with th.no_grad():
        return th.cat(model.critic(observations, actions), dim=1).min(dim=1).values


def anchor_share(model: IQL, observations: th.Tensor, data_actions: th.Tensor) -> float:
    """The anchor's share of the norm of the ``ddpg_awr`` loss's gradient with respect to the actor's actions."""
    with th.no_grad():
        q_data = model.target_q_values(observations, data_actions)
        weights = th.exp(model.temperature * (q_data - model.state_values(observations))).clamp(max=model.max_weight)
        weights = (weights / weights.mean()).squeeze(1)
    mean_actions, _, _ = model.actor.get_action_dist_params(observations)
    actions = th.tanh(mean_actions).detach().requires_grad_(True)
    q_pi = th.cat(model.critic(observations, actions), dim=1).min(dim=1).values
    q_loss = -q_pi.mean() / q_pi.abs().mean().detach().clamp(min=1e-6)
    anchor = model.actor_bc_weight * (weights * (actions - data_actions).pow(2).mean(dim=-1)).mean()
    (q_grad,) = th.autograd.grad(q_loss, actions)
    (anchor_grad,) = th.autograd.grad(anchor, actions)
    q_norm, anchor_norm = q_grad.norm().item(), anchor_grad.norm().item()
    return anchor_norm / max(q_norm + anchor_norm, 1e-12)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python research/scripts/finetune_drift.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("start", metavar="START.zip")
    parser.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT.zip")
    parser.add_argument("--buffer", required=True, metavar="PKL")
    parser.add_argument("--algo", default="iql", choices=("iql", *VARIANTS))
    parser.add_argument("--states", type=positive_int, default=2000)
    parser.add_argument("--window", type=positive_int, default=10000)
    parser.add_argument("--threads", type=positive_int, default=1)
    args = parser.parse_args(argv)
    missing = [path for path in (args.start, *args.checkpoints, args.buffer) if not pathlib.Path(path).is_file()]
    if missing:
        raise SystemExit(f"error: no file {missing[0]}")
    th.set_num_threads(args.threads)
    algorithm = load_class(args.algo)

    try:
        start = algorithm.load(args.start, device="cpu")
        offline = start.load_offline_data()
        buffer = load_from_pkl(args.buffer)
    except Exception as error:  # a file of another kind or algorithm: one line, not a traceback
        raise SystemExit(f"error: {type(error).__name__}: {error}") from None
    online = buffer.online if isinstance(buffer, MixedReplayBuffer) else buffer  # a fine-tuning checkpoint's, or a plain one
    off_obs, off_act, off_rew, off_ends = buffer_rows(offline)
    on_obs, on_act, on_rew, on_ends = buffer_rows(online)
    observations, data_actions = probe_states(offline, online, args.states)
    start_actions = deterministic(start, observations)

    print(f"{'checkpoint':<40} |da| arm  |da| fingers  Q(a) - Q(a_start)  Q(a) - V   anchor share")
    for path in [args.start, *args.checkpoints]:
        try:
            model = start if path == args.start else algorithm.load(path, device="cpu")
        except Exception as error:
            raise SystemExit(f"error: {path}: {type(error).__name__}: {error}") from None
        model.policy.set_training_mode(False)
        actions = deterministic(model, observations)
        change = (actions - start_actions).abs()
        q_own, q_start = twin_min(model, observations, actions), twin_min(model, observations, start_actions)
        with th.no_grad():
            advantage = q_own - model.state_values(observations).squeeze(1)
        share = anchor_share(model, observations, data_actions)
        name = "/".join(pathlib.Path(path).parts[-2:])
        print(f"{name:<40} {change[:, ARM].mean():>8.3f}  {change[:, FINGERS].mean():>12.3f}  "
              f"{(q_own - q_start).mean():>+17.4f}  {advantage.mean():>+8.4f}  {share:>12.2f}")  # fmt: skip

    print("closings at 50-90 deg   episodes  closings  lifted  reopened  hand rise (cm)  object rise (cm)")
    data = list(episodes(off_obs, off_act, off_rew, off_ends))
    print(closing_row("offline data", len(data), [o for _, *episode in data for o in closing_outcomes(*episode)]))
    by_window: dict[int, list] = {}
    for first, *episode in episodes(on_obs, on_act, on_rew, on_ends):
        by_window.setdefault(first // args.window, []).append(episode)
    for window, members in sorted(by_window.items()):
        label = f"online {window * args.window}-{(window + 1) * args.window}"
        print(closing_row(label, len(members), [o for episode in members for o in closing_outcomes(*episode)]))


if __name__ == "__main__":
    main()
