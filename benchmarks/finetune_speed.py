"""Online fine-tuning's env steps/s and gradient steps/s at the shipped configs, one action a state and in action
chunks, next to SB3's SAC on the same task.

    python benchmarks/finetune_speed.py [--env PandaForce-v0] [--steps 300] [--rounds 3] [--threads 1]

Our CQL gets the settings of ``hyperparams/cql.yml`` (networks, batch, sampled actions, rewards, anchor) and of
``hyperparams/cql_finetune.yml`` (online fraction, one gradient step per env step), calibrated (``CalQL``),
with an offline part of 20,000 random Panda-shaped transitions (the speed does not depend on what they hold). The
chunked config is the same model with ``action_chunk: 5`` and the config's ``chunked`` settings (one gradient step per
chunk of 5 env steps, pink noise), uncalibrated (calibration is not supported with chunks). SB3's SAC gets the same
networks, batch and training frequency as the first, and no offline data. Each round runs ``--steps`` env steps of
each, back to back, in the task's env with the config's action mode; medians are reported, and for the ratios the
median of the rounds' ratios. The env alone (random actions) is timed in the same rounds: what is left of a step is
the policy's action and the gradient step.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
import yaml
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.noise import ActionNoise, NormalActionNoise

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL, CalQL
from sb3_cql.common import HeldActionNoise, pink_action_noise
from sb3_cql.zoo.plugin import hyperparams_dir

N_OFFLINE = 20_000
#: Keys of the zoo configs that are not CQL's keywords.
ZOO_ONLY = {"policy", "dataset", "env_kwargs", "n_timesteps", "monitor_kwargs", "eval_freq", "n_eval_episodes",
            "save_freq", "noise_type", "noise_std", "noise_hold", "callback"}  # fmt: skip
#: The config's callback that sets the exploration noise (sb3_cql.zoo.callbacks).
NOISE_CALLBACK = "sb3_cql.zoo.callbacks.ExplorationNoise"
#: The chunk length of the chunked config.
CHUNK = 5


def config(env_id: str, chunked: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(CQL's keywords, env kwargs)`` of the offline config of Panda-v0 and the fine-tuning config of ``env_id``;
    ``chunked``: of a model of :data:`CHUNK` actions a chunk, with ``cql_finetune_chunked.yml``.
    The action noise is ``("normal" or "pink", std, hold)``, made for the env's action space by :func:`make_noise`."""
    offline = yaml.safe_load((hyperparams_dir() / "cql.yml").read_text())["Panda-v0"]
    online_config = "cql_finetune_chunked.yml" if chunked else "cql_finetune.yml"
    online = yaml.safe_load((hyperparams_dir() / online_config).read_text())[env_id]
    for entry in online.get("callback") or []:  # ExplorationNoise's keywords as the noise keys they stand for
        if isinstance(entry, dict) and NOISE_CALLBACK in entry:
            noise = entry[NOISE_CALLBACK]
            if noise.get("pink_std") is not None:
                online = {**online, "noise_type": "pink", "noise_std": noise["pink_std"]}
            online = {**online, "noise_hold": noise.get("hold", 1)}
    settings = {key: value for key, value in {**offline, **online}.items() if key not in ZOO_ONLY}
    settings["policy_kwargs"] = eval(settings["policy_kwargs"]) if "policy_kwargs" in settings else None
    if online.get("noise_type", "normal") not in ("normal", "pink"):
        raise ValueError(f"noise_type {online['noise_type']!r}: only 'normal' and 'pink' noise are timed here")
    if "noise_std" in online:
        settings["action_noise"] = (
            online.get("noise_type", "normal"),
            float(online["noise_std"]),
            online.get("noise_hold", 1),
        )
    if chunked:
        settings["action_chunk"] = CHUNK
    return settings, online.get("env_kwargs", {})


def make_noise(noise: tuple[str, float, int], env: gym.Env) -> ActionNoise:
    """The action noise of :func:`config`, as the zoo (with our plugin) makes it."""
    kind, std, hold = noise
    dim = env.action_space.shape[0]
    made = pink_action_noise(std, dim, env.spec.max_episode_steps, seed=0) if kind == "pink" else \
        NormalActionNoise(np.zeros(dim), np.full(dim, std))  # fmt: skip
    return HeldActionNoise(made, hold) if hold > 1 else made


def offline_buffer(env: gym.Env) -> ReplayBuffer:
    """Random transitions of the env's shapes, in episodes of 700 steps (with returns-to-go when calibrated)."""
    buffer = ReplayBuffer(N_OFFLINE, env.observation_space, env.action_space)
    rng = np.random.default_rng(0)
    buffer.observations[:] = rng.standard_normal(buffer.observations.shape)
    buffer.next_observations[:] = rng.standard_normal(buffer.next_observations.shape)
    buffer.actions[:] = rng.uniform(-1, 1, buffer.actions.shape)
    buffer.dones[699::700] = 1.0
    buffer.timeouts[699::700] = 1.0
    buffer.full = True
    return buffer


def cql_steps_per_s(env: gym.Env, settings: dict[str, Any], steps: int) -> tuple[float, float]:
    """``(env steps/s, gradient steps/s)`` of our CQL fine-tuning (calibrated, unless in chunks)."""
    settings = {**settings, "policy_kwargs": dict(settings["policy_kwargs"])}  # SB3 writes into it
    if "action_noise" in settings:
        settings["action_noise"] = make_noise(settings["action_noise"], env)
    calibrated = settings.get("action_chunk", 1) == 1
    model = (CalQL if calibrated else CQL)("MlpPolicy", env, dataset=offline_buffer(env), seed=0, **settings)
    model.set_logger(Logger(None, []))
    model.learn(10)
    updates, start = model._n_updates, time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    elapsed = time.perf_counter() - start
    return steps / elapsed, (model._n_updates - updates) / elapsed


def sac_steps_per_s(env: gym.Env, settings: dict[str, Any], steps: int) -> tuple[float, float]:
    """``(env steps/s, gradient steps/s)`` of SB3's SAC with the same networks, batch and training frequency."""
    same = {key: settings[key] for key in ("batch_size", "gamma", "tau", "train_freq", "gradient_steps") if key in settings}
    model = SAC("MlpPolicy", env, learning_starts=0, policy_kwargs=dict(settings["policy_kwargs"]), seed=0, **same)
    model.set_logger(Logger(None, []))
    model.learn(max(10, settings.get("batch_size", 256)))  # enough transitions for a batch
    updates, start = model._n_updates, time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    elapsed = time.perf_counter() - start
    return steps / elapsed, (model._n_updates - updates) / elapsed


def env_steps_per_s(env: gym.Env, steps: int) -> float:
    env.reset(seed=0)
    env.action_space.seed(0)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="PandaForce-v0", choices=sorted(envs.ENV_IDS))
    parser.add_argument("--steps", type=int, default=300, help="env steps of each measurement")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: as the measured fine-tuning runs)")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    settings, env_kwargs = config(args.env)
    chunked, _ = config(args.env, chunked=True)
    env = gym.make(args.env, **env_kwargs)
    print(f"# {args.env} {env_kwargs}, batch {settings.get('batch_size')}, {settings['policy_kwargs']}, "
          f"{settings.get('cql_n_actions')} sampled actions, online fraction {settings.get('online_fraction')}, "
          f"{args.threads} thread(s), medians of {args.rounds} rounds of {args.steps} env steps")  # fmt: skip
    results: dict[str, list[tuple[float, float]]] = {"cql": [], "chunked": [], "sac": []}
    alone: list[float] = []
    for _ in range(args.rounds):
        results["cql"].append(cql_steps_per_s(env, settings, args.steps))
        results["chunked"].append(cql_steps_per_s(env, chunked, args.steps))
        results["sac"].append(sac_steps_per_s(env, settings, args.steps))
        alone.append(env_steps_per_s(env, 5 * args.steps))
    names = {"cql": "our CQL fine-tuning", "chunked": f"chunked (h {CHUNK})", "sac": "SB3 SAC"}
    for key, name in names.items():
        env_rate = statistics.median(rate for rate, _ in results[key])
        gradient_rate = statistics.median(rate for _, rate in results[key])
        print(f"{name:20s} {env_rate:8.2f} env steps/s {gradient_rate:8.2f} gradient steps/s")
    for key, reference in (("cql", "sac"), ("chunked", "cql"), ("chunked", "sac")):
        ratio = statistics.median(ours[0] / other[0] for ours, other in zip(results[key], results[reference], strict=True))
        print(f"{names[key]} / {names[reference]} (env steps/s): {ratio:.2f} (median of the rounds' ratios)")
    print(f"env alone, random actions: {statistics.median(alone):.0f} steps/s")


if __name__ == "__main__":
    main()
