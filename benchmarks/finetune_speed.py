"""Online fine-tuning's env steps/s and gradient steps/s at the shipped configs (CQL one action a state and in action
chunks, IQL), next to SB3's SAC on the same task.

    python benchmarks/finetune_speed.py [--env PandaForce-v0] [--steps 300] [--rounds 3] [--threads 1]

Our CQL gets the settings of ``hyperparams/cql.yml`` (networks, batch, sampled actions, rewards, anchor) and of
``hyperparams/cql_finetune.yml`` (online fraction, one gradient step per env step), calibrated (``CalQL``); in chunks,
the same model with ``action_chunk: 5`` and ``hyperparams/cql_finetune_chunked.yml`` (one gradient step per chunk of 5
env steps, pink noise), uncalibrated. Our IQL gets ``hyperparams/iql_yaw.yml`` (the random-yaw recipe: 3 x 256
networks, batch 256, 25-step returns, the averaged actor) and ``hyperparams/iql_finetune.yml``. Each has an offline
part of 20,000 random Panda-shaped transitions (the speed does not depend on what they hold), and each is timed beside
SB3's SAC with its networks, batch and training frequency and no offline data. Each round runs ``--steps`` env steps
of each, back to back, in the task's env with the config's action mode; medians are reported, and for the ratios the
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
from sb3_cql import CQL, IQL, CalQL
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


#: The configs timed: ``(offline config, its entry, fine-tuning config)`` by name.
CONFIGS = {
    "cql": ("cql.yml", "Panda-v0", "cql_finetune.yml"),
    "chunked": ("cql.yml", "Panda-v0", "cql_finetune_chunked.yml"),
    "iql": ("iql_yaw.yml", "PandaForce-v0", "iql_finetune.yml"),
}


def config(env_id: str, name: str = "cql") -> tuple[dict[str, Any], dict[str, Any]]:
    """``(the algorithm's keywords, env kwargs)`` of the offline config and the fine-tuning config of ``env_id`` named
    in :data:`CONFIGS`; ``"chunked"``: of a CQL model of :data:`CHUNK` actions a chunk, with
    ``cql_finetune_chunked.yml``. The action noise is ``("normal" or "pink", std, hold)``, made for the env's action
    space by :func:`make_noise`."""
    offline_config, entry, online_config = CONFIGS[name]
    offline = yaml.safe_load((hyperparams_dir() / offline_config).read_text())[entry]
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
    if name == "chunked":
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


def ours_steps_per_s(env: gym.Env, settings: dict[str, Any], steps: int, name: str = "cql") -> tuple[float, float]:
    """``(env steps/s, gradient steps/s)`` of our fine-tuning of the config ``name`` (CQL calibrated, unless in
    chunks)."""
    settings = {**settings, "policy_kwargs": dict(settings["policy_kwargs"])}  # SB3 writes into it
    if "action_noise" in settings:
        settings["action_noise"] = make_noise(settings["action_noise"], env)
    algorithm = {"cql": CalQL, "chunked": CQL, "iql": IQL}[name]
    model = algorithm("MlpPolicy", env, dataset=offline_buffer(env), seed=0, **settings)
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
    parser.add_argument(
        "--only",
        nargs="+",
        choices=sorted(CONFIGS),
        default=sorted(CONFIGS),
        help="the configs to time (each beside SB3's SAC at its networks, batch and frequency)",
    )
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    settings = {name: config(args.env, name) for name in args.only}
    env = gym.make(args.env, **next(iter(settings.values()))[1])
    for name, (keywords, env_kwargs) in settings.items():
        print(f"# {name}: {args.env} {env_kwargs}, batch {keywords.get('batch_size')}, {keywords['policy_kwargs']}, "
              f"online fraction {keywords.get('online_fraction')}, n_steps {keywords.get('n_steps', 1)}")  # fmt: skip
    print(f"# {args.threads} thread(s), medians of {args.rounds} rounds of {args.steps} env steps, side by side")
    results: dict[str, list[tuple[float, float]]] = {key: [] for name in args.only for key in (name, f"sac-{name}")}
    alone: list[float] = []
    for _ in range(args.rounds):
        for name, (keywords, _) in settings.items():
            results[name].append(ours_steps_per_s(env, keywords, args.steps, name))
            results[f"sac-{name}"].append(sac_steps_per_s(env, keywords, args.steps))
        alone.append(env_steps_per_s(env, 5 * args.steps))
    names = {"cql": "our CQL fine-tuning", "chunked": f"CQL in chunks (h {CHUNK})", "iql": "our IQL fine-tuning"}
    for key, values in results.items():
        label = f"SB3 SAC as {key[4:]}" if key.startswith("sac-") else names[key]
        env_rate = statistics.median(rate for rate, _ in values)
        gradient_rate = statistics.median(rate for _, rate in values)
        print(f"{label:28s} {env_rate:8.2f} env steps/s {gradient_rate:8.2f} gradient steps/s")
    for name in args.only:
        pairs = zip(results[name], results[f"sac-{name}"], strict=True)
        ratio = statistics.median(ours[0] / sac[0] for ours, sac in pairs)
        print(f"{names[name]} / SB3 SAC at its settings (env steps/s): {ratio:.2f} (median of the rounds' ratios)")
    print(f"env alone, random actions: {statistics.median(alone):.0f} steps/s")


if __name__ == "__main__":
    main()
