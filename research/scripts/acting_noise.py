"""How a SAC-style actor's exploration (a sample of its distribution, or its deterministic action plus noise) changes
its success on a task, and where the sampled actions leave the deterministic ones.

Usage: python research/scripts/acting_noise.py MODEL.zip [--algo cql] [--env PandaForce-v0] [--seeds 60000-60019]
           [--modes mean sample normal:0.1 ou:0.1 pink:0.1 held:0.1] [--open-loop] [--threads N]

Each mode plays the episodes reset with ``--seeds`` (one episode per seed: the same episodes for every mode) in the
action mode the model was trained in, and prints its success rate:

- ``mean``: the deterministic action (what evaluations use);
- ``sample``: a sample of the actor's tanh-Gaussian, as SAC's ``collect_rollouts`` acts;
- ``normal:SIGMA``: the deterministic action plus N(0, SIGMA) noise per dimension, clipped to [-1, 1] (SB3's
  ``NormalActionNoise``, as ``action_noise`` adds it in ``collect_rollouts``);
- ``ou:SIGMA``: the same with SB3's ``OrnsteinUhlenbeckActionNoise`` (temporally correlated), reset every episode;
- ``pink:SIGMA``: the same with pink noise (``pink-noise-rl``'s, :func:`sb3_cql.common.pink_action_noise`, sequences of
  an episode's length, seeded by the episode's seed);
- ``held:SIGMA``: N(0, SIGMA) drawn once per action chunk (the model's ``action_chunk`` steps) and held through it
  (:class:`sb3_cql.common.HeldActionNoise`), reset every episode.

Every mode also prints how far it moves the wrist and where the fingers close: the root mean square of the wrist
joint's (the 7th arm joint's) change over 100 steps (every 100-step window starting at a multiple of 10 steps), the
same of the noise's own push on the wrist's target (what the noise, or the sample, adds to the action, times the
target's change per unit of action: ``arm_max_delta`` in delta actions, summed over the window), and of
the episodes whose fingers close on a cylinder lying on its side, how many close within 20 degrees of across its axis
at least once (:func:`envs.pd_controller.closing_angles` of 70 degrees or more: the hand turned to the fallen cylinder).

For ``sample`` it also prints, per action dimension (7 arm joints, then the two fingers), the actor's mean standard
deviation before the tanh over the visited states, the mean absolute difference between sampled and deterministic
actions, and the fraction of steps whose sampled finger command has the other sign than the deterministic one (in
delta mode the data's gripper commands are +1 open, -1 close: a flipped sign opens a closed gripper). Output::

    mean: success 0.250 (5/20)
      wrist's 100-step change 14.7 deg (RMS), the noise's push on its target 0.0 deg; closings on a lying cylinder
      in 9 episodes, 3 within 20 deg of across it
    sample: success 0.000 (0/20)
      wrist's ...
      std before tanh [...]
      |sample - mean| [...]
      finger sign flips [...]

A model of action chunks (``action_chunk`` > 1) is asked without a state at each step, so it acts with the first
action of a new chunk at every step (closed loop), where ``sb3_cql.evaluate`` and fine-tuning run each chunk open
loop; ``--open-loop`` runs each chunk open loop too (the noise added to each of its actions, as fine-tuning acts).

Use seeds outside the protocol's evaluation seeds (117, 12321, 7456, 3426, 573) and outside ``--seeds`` of any
evaluation the findings compare with; nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from _cli import positive_int
from stable_baselines3.common.noise import ActionNoise, NormalActionNoise, OrnsteinUhlenbeckActionNoise

import envs  # noqa: F401  (registers the tasks)
from envs.pd_controller import closing_angles
from sb3_cql.common import HeldActionNoise, pink_action_noise
from sb3_cql.evaluate import env_kwargs_for, load_policy, parse_seeds

MODES = "mean, sample, normal:SIGMA, ou:SIGMA, pink:SIGMA or held:SIGMA with SIGMA >= 0"
#: The wrist: the 7th arm joint of the observation's joint positions.
WRIST = 6
#: Steps over which the wrist's change is measured, and the step between two windows.
WINDOW, WINDOW_STRIDE = 100, 10
#: A closing at this angle or more (degrees between the closing direction and a lying cylinder's axis) is within 20
#: degrees of across the axis.
TURNED = 70.0


def make_noise(mode: str, n_actions: int, hold: int = 1, seq_len: int = 700, seed: int = 0) -> ActionNoise | None:
    """The SB3 action noise of a ``normal:SIGMA``, ``ou:SIGMA``, ``pink:SIGMA`` (sequences of ``seq_len`` steps from
    ``seed``) or ``held:SIGMA`` (each N(0, SIGMA) draw held for ``hold`` steps) mode; ``None`` for ``mean`` and
    ``sample``."""
    if mode in ("mean", "sample"):
        return None
    kind, _, sigma_text = mode.partition(":")
    try:
        sigma = float(sigma_text)
    except ValueError:
        sigma = -1.0
    if kind not in ("normal", "ou", "pink", "held") or not sigma >= 0:
        raise ValueError(f"unknown mode {mode!r}: {MODES}")
    if kind == "pink":
        return pink_action_noise(sigma, n_actions, seq_len, seed=seed)
    noise_class = OrnsteinUhlenbeckActionNoise if kind == "ou" else NormalActionNoise
    noise = noise_class(mean=np.zeros(n_actions), sigma=sigma * np.ones(n_actions))
    return HeldActionNoise(noise, hold) if kind == "held" else noise


def window_sums(increments: np.ndarray) -> np.ndarray:
    """The sums of an episode's per-step ``increments`` over every :data:`WINDOW`-step window that starts at a
    multiple of :data:`WINDOW_STRIDE`."""
    totals = np.concatenate([[0.0], np.cumsum(increments)])
    starts = np.arange(0, len(totals) - WINDOW, WINDOW_STRIDE)
    return totals[starts + WINDOW] - totals[starts]


def wrist_changes(observations: np.ndarray) -> np.ndarray:
    """The wrist joint's change (rad) over every :data:`WINDOW`-step window of an episode's observations
    (:func:`window_sums` of its step-to-step changes)."""
    wrist = np.asarray(observations)[:, envs.OBSERVATION_SLICES["joint_positions"]][:, WRIST]
    return window_sums(np.diff(wrist))


def target_scale(env: gym.Env) -> float:
    """How far (rad) an action of 1 on the wrist moves its target: ``arm_max_delta`` in delta actions, half the
    joint's range in absolute ones (where the action is the target)."""
    robot = env.unwrapped.robot
    if robot.action_mode == "delta":
        return float(robot.max_delta[WRIST])
    return float((env.action_space.high[WRIST] - env.action_space.low[WRIST]) / 2)


def play(
    model: Any, env_id: str, env_kwargs: dict[str, Any], seeds: range, mode: str, open_loop: bool = False
) -> dict[str, Any]:
    """Success per episode of ``model`` acting in ``mode``, the wrist's 100-step changes and each episode's closing
    angles on a lying cylinder; for ``sample``, the per-dimension statistics too. ``open_loop``: a chunked model runs
    each chunk open loop (through ``predict``'s state)."""
    env = gym.make(env_id, **env_kwargs)
    hold, seq_len, scale = getattr(model, "action_chunk", 1), env.spec.max_episode_steps or 1000, target_scale(env)
    successes, stds, gaps, flips, changes, pushes, lying = [], [], [], [], [], [], []
    try:
        for seed in seeds:
            observation, info = env.reset(seed=int(seed))
            noise = make_noise(mode, env.action_space.shape[0], hold, seq_len, int(seed))
            observations, pushed, state, done = [observation], [], None, False
            while not done:
                if open_loop:
                    action, state = model.predict(
                        observation, state, np.array([state is None]), deterministic=mode != "sample"
                    )
                else:
                    action, _ = model.predict(observation, deterministic=mode != "sample")
                if mode == "sample":
                    observation_tensor, _ = model.policy.obs_to_tensor(observation)
                    with th.no_grad():
                        mean_actions, log_std, _ = model.actor.get_action_dist_params(observation_tensor)
                    deterministic = th.tanh(mean_actions).numpy()[0]
                    stds.append(log_std.exp().numpy()[0])
                    gaps.append(np.abs(action - deterministic))
                    flips.append(np.sign(action[-2:]) != np.sign(deterministic[-2:]))
                    pushed.append((action[WRIST] - deterministic[WRIST]) * scale)
                elif noise is not None:
                    noisy = np.clip(action + noise(), -1.0, 1.0)
                    pushed.append((noisy[WRIST] - np.clip(action[WRIST], -1.0, 1.0)) * scale)
                    action = noisy
                else:
                    pushed.append(0.0)
                observation, _, terminated, truncated, info = env.step(action)
                observations.append(observation)
                done = terminated or truncated
            successes.append(bool(info.get("is_success", False)))
            changes.append(wrist_changes(np.array(observations)))
            pushes.append(window_sums(np.array(pushed)))
            lying.append([angle for angle in closing_angles(np.array(observations)) if angle is not None])
    finally:
        env.close()
    result: dict[str, Any] = {"successes": successes, "wrist_changes": np.concatenate(changes),
                              "wrist_pushes": np.concatenate(pushes), "lying_closings": lying}  # fmt: skip
    if mode == "sample":
        result.update(std=np.mean(stds, axis=0), gap=np.mean(gaps, axis=0), flips=np.mean(flips, axis=0))
    return result


def exploration_line(result: dict[str, Any]) -> str:
    """How far the wrist moved and how the fingers closed, from :func:`play`'s ``result``."""
    change, push = (_rms_degrees(result[key]) for key in ("wrist_changes", "wrist_pushes"))
    closing = [angles for angles in result["lying_closings"] if angles]
    turned = sum(max(angles) >= TURNED for angles in closing)
    return (f"  wrist's {WINDOW}-step change {change:.1f} deg (RMS), the noise's push on its target {push:.1f} deg; "
            f"closings on a lying cylinder in {len(closing)} episodes, {turned} within 20 deg of across it")  # fmt: skip


def _rms_degrees(values: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(values**2)))) if len(values) else float("nan")


def parse_mode(text: str) -> str:
    """A ``--modes`` item, checked: one of :data:`MODES`."""
    try:
        make_noise(text, 1)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def _fmt(values: np.ndarray) -> str:
    return "[" + " ".join(f"{value:.3f}" for value in values) + "]"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/acting_noise.py",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("model", help="a saved SAC-style model (cql, sac, bc)")
    parser.add_argument("--algo", default="cql", help="RL-Zoo3 name of its algorithm (default cql)")
    parser.add_argument("--env", default="PandaForce-v0", choices=list(envs.ENV_IDS))
    parser.add_argument("--seeds", type=parse_seeds, default=range(60000, 60020), help="episode seeds, e.g. 60000-60019")
    parser.add_argument("--modes", nargs="+", type=parse_mode, default=["mean", "sample", "normal:0.1", "ou:0.1"])
    parser.add_argument("--open-loop", action="store_true", help="run a chunked model's chunks open loop, as fine-tuning")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = load_policy(args.model, args.algo, args.env)
        env_kwargs = env_kwargs_for(model, args.env)
    except (ValueError, OSError) as error:
        sys.exit(f"error: {error}")
    for mode in args.modes:
        result = play(model, args.env, env_kwargs, args.seeds, mode, args.open_loop)
        wins, total = sum(result["successes"]), len(result["successes"])
        print(f"{mode}: success {wins / total:.3f} ({wins}/{total})", flush=True)
        print(exploration_line(result), flush=True)
        if mode == "sample":
            print(f"  std before tanh {_fmt(result['std'])}")
            print(f"  |sample - mean| {_fmt(result['gap'])}")
            print(f"  finger sign flips {_fmt(result['flips'])}", flush=True)


if __name__ == "__main__":
    main()
