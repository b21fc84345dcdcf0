"""How a SAC-style actor's exploration (a sample of its distribution, or its deterministic action plus noise) changes
its success on a task, and where the sampled actions leave the deterministic ones.

Usage: python experiments/acting_noise.py MODEL.zip [--algo cql] [--env PandaForce-v0] [--seeds 60000-60019]
           [--modes mean sample normal:0.1 ou:0.1] [--threads N]

Each mode plays the episodes reset with ``--seeds`` (one episode per seed: the same episodes for every mode) in the
action mode the model was trained in, and prints its success rate:

- ``mean``: the deterministic action (what evaluations use);
- ``sample``: a sample of the actor's tanh-Gaussian, as SAC's ``collect_rollouts`` acts;
- ``normal:SIGMA``: the deterministic action plus N(0, SIGMA) noise per dimension, clipped to [-1, 1] (SB3's
  ``NormalActionNoise``, as ``action_noise`` adds it in ``collect_rollouts``);
- ``ou:SIGMA``: the same with SB3's ``OrnsteinUhlenbeckActionNoise`` (temporally correlated), reset every episode.

For ``sample`` it also prints, per action dimension (7 arm joints, then the two fingers), the actor's mean standard
deviation before the tanh over the visited states, the mean absolute difference between sampled and deterministic
actions, and the fraction of steps whose sampled finger command has the other sign than the deterministic one (in
delta mode the data's gripper commands are +1 open, -1 close: a flipped sign opens a closed gripper). Output::

    mean: success 0.250 (5/20)
    sample: success 0.000 (0/20)
      std before tanh [...]
      |sample - mean| [...]
      finger sign flips [...]

A model of action chunks (``action_chunk`` > 1) is asked without a state at each step, so it acts with the first
action of a new chunk at every step (closed loop), where ``sb3_cql.evaluate`` runs each chunk open loop.

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
from sb3_cql.evaluate import env_kwargs_for, load_policy, parse_seeds


def make_noise(mode: str, n_actions: int) -> ActionNoise | None:
    """The SB3 action noise of a ``normal:SIGMA`` or ``ou:SIGMA`` mode; ``None`` for ``mean`` and ``sample``."""
    if mode in ("mean", "sample"):
        return None
    kind, _, sigma_text = mode.partition(":")
    noise_class = {"normal": NormalActionNoise, "ou": OrnsteinUhlenbeckActionNoise}.get(kind)
    try:
        sigma = float(sigma_text)
    except ValueError:
        sigma = -1.0
    if noise_class is None or not sigma >= 0:
        raise ValueError(f"unknown mode {mode!r}: mean, sample, normal:SIGMA or ou:SIGMA with SIGMA >= 0")
    return noise_class(mean=np.zeros(n_actions), sigma=sigma * np.ones(n_actions))


def play(model: Any, env_id: str, env_kwargs: dict[str, Any], seeds: range, mode: str) -> dict[str, Any]:
    """Success per episode of ``model`` acting in ``mode``; for ``sample``, the per-dimension statistics too."""
    env = gym.make(env_id, **env_kwargs)
    noise = make_noise(mode, env.action_space.shape[0])
    successes, stds, gaps, flips = [], [], [], []
    try:
        for seed in seeds:
            observation, info = env.reset(seed=int(seed))
            if noise is not None:
                noise.reset()
            done = False
            while not done:
                action, _ = model.predict(observation, deterministic=mode != "sample")
                if mode == "sample":
                    observation_tensor, _ = model.policy.obs_to_tensor(observation)
                    with th.no_grad():
                        mean_actions, log_std, _ = model.actor.get_action_dist_params(observation_tensor)
                    deterministic = th.tanh(mean_actions).numpy()[0]
                    stds.append(log_std.exp().numpy()[0])
                    gaps.append(np.abs(action - deterministic))
                    flips.append(np.sign(action[-2:]) != np.sign(deterministic[-2:]))
                elif noise is not None:
                    action = np.clip(action + noise(), -1.0, 1.0)
                observation, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
            successes.append(bool(info.get("is_success", False)))
    finally:
        env.close()
    result: dict[str, Any] = {"successes": successes}
    if mode == "sample":
        result.update(std=np.mean(stds, axis=0), gap=np.mean(gaps, axis=0), flips=np.mean(flips, axis=0))
    return result


def parse_mode(text: str) -> str:
    """A ``--modes`` item, checked: ``mean``, ``sample``, ``normal:SIGMA`` or ``ou:SIGMA``."""
    try:
        make_noise(text, 1)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def _fmt(values: np.ndarray) -> str:
    return "[" + " ".join(f"{value:.3f}" for value in values) + "]"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python experiments/acting_noise.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("model", help="a saved SAC-style model (cql, sac, bc)")
    parser.add_argument("--algo", default="cql", help="RL-Zoo3 name of its algorithm (default cql)")
    parser.add_argument("--env", default="PandaForce-v0", choices=list(envs.ENV_IDS))
    parser.add_argument("--seeds", type=parse_seeds, default=range(60000, 60020), help="episode seeds, e.g. 60000-60019")
    parser.add_argument("--modes", nargs="+", type=parse_mode, default=["mean", "sample", "normal:0.1", "ou:0.1"])
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = load_policy(args.model, args.algo, args.env)
        env_kwargs = env_kwargs_for(model, args.env)
    except (ValueError, OSError) as error:
        sys.exit(f"error: {error}")
    for mode in args.modes:
        result = play(model, args.env, env_kwargs, args.seeds, mode)
        wins, total = sum(result["successes"]), len(result["successes"])
        print(f"{mode}: success {wins / total:.3f} ({wins}/{total})", flush=True)
        if mode == "sample":
            print(f"  std before tanh {_fmt(result['std'])}")
            print(f"  |sample - mean| {_fmt(result['gap'])}")
            print(f"  finger sign flips {_fmt(result['flips'])}", flush=True)


if __name__ == "__main__":
    main()
