"""Our CQL, IQL and BC beside d3rlpy's CQL, IQL and BC, each at its own defaults, on two small tasks of hand-made data.

    python benchmarks/d3rlpy_check.py --d3rlpy-python /path/to/venv/bin/python [--tasks pendulum mountaincar]
        [--seeds 0 1 2] [--steps 10000] [--episodes N] [--eval-episodes 10] [--threads 1] [--output FILE.jsonl]
        [--libraries sb3-cql d3rlpy]

The data, made here from a seeded script, are the same arrays for both libraries:

- ``pendulum``: Pendulum-v1, 100 episodes (200 steps, all truncated) of an energy-pumping swing-up controller with a
  PD hold at the top, N(0, 0.5) torque noise, and at each step, with a probability drawn per episode from U(0.4, 1),
  a uniform random torque instead: a medium policy. Scored by the mean return.
- ``mountaincar``: MountainCarContinuous-v0, 100 episodes (999-step limit) of a controller that pushes along the car's
  velocity with a strength drawn per episode from U(0, 0.2), plus N(0, 1) noise, clipped to [-1, 1]: some of its
  episodes reach the flag, most of the weak ones do not. Scored by the success rate (the episode terminated at the
  flag). The script prints the data's own score first.

Ours train from an SB3 ``ReplayBuffer`` (``dataset=``, actions scaled to [-1, 1], truncations as timeouts) with every
constructor keyword at its default; d3rlpy's (``CQLConfig()``, ``IQLConfig()``, ``BCConfig()``) from an
``MDPDataset`` of the same arrays with its defaults, plus the ``MinMaxActionScaler`` of the env's action bounds that
its tanh policies need for Pendulum-v1's [-2, 2] (the same scaling as ours). d3rlpy runs in the interpreter given by
``--d3rlpy-python`` (it pins gymnasium 1.0.0: ``python -m venv V && V/bin/pip install torch==2.13.0 d3rlpy==2.8.1``).
Each algorithm makes ``--steps`` gradient steps from each seed, and its last policy acts deterministically in
``--eval-episodes`` episodes whose env seeds are 10000 onwards (the data's are 0 onwards). One JSON line per run goes
to ``--output``; a table of the means over seeds (and their range) is printed at the end.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_cql import BC, CQL, IQL

TASKS = {"pendulum": "Pendulum-v1", "mountaincar": "MountainCarContinuous-v0"}
EVAL_SEED = 10_000
STEP_KEYS = ("observations", "next_observations", "actions", "rewards", "terminations", "truncations")

D3RLPY_SCRIPT = r"""
import json, sys, time
import gymnasium as gym, numpy as np, torch, d3rlpy
data_path, algo_name, seed, steps, eval_episodes, threads, EVAL_SEED = sys.argv[1:6] + [int(sys.argv[6]), int(sys.argv[7])]
torch.set_num_threads(threads)
d3rlpy.seed(int(seed))
data = np.load(data_path)
env = gym.make(str(data["env_id"]))
dataset = d3rlpy.dataset.MDPDataset(data["observations"], data["actions"], data["rewards"], data["terminations"],
                                    timeouts=data["truncations"])
scaler = d3rlpy.preprocessing.MinMaxActionScaler(minimum=env.action_space.low, maximum=env.action_space.high)
config = {"cql": d3rlpy.algos.CQLConfig, "iql": d3rlpy.algos.IQLConfig, "bc": d3rlpy.algos.BCConfig}[algo_name]
algo = config(action_scaler=scaler).create(device="cpu:0")
start = time.perf_counter()
algo.fit(dataset, n_steps=int(steps), n_steps_per_epoch=int(steps), show_progress=False, save_interval=10**9,
         logger_adapter=d3rlpy.logging.NoopAdapterFactory())
seconds = time.perf_counter() - start
returns, successes = [], []
for episode in range(int(eval_episodes)):
    observation, _ = env.reset(seed=EVAL_SEED + episode)
    done, total = False, 0.0
    while not done:
        action = algo.predict(observation[None].astype(np.float32))[0]
        observation, reward, terminated, truncated, _ = env.step(action)
        total, done = total + reward, terminated or truncated
    returns.append(total)
    successes.append(bool(terminated))
print(json.dumps({"returns": returns, "successes": successes, "seconds": seconds}))
"""


def pendulum_action(observation: np.ndarray, rng: np.random.Generator, random_rate: float) -> np.ndarray:
    """Swing up by pumping energy, hold upright with a PD law, N(0, 0.5) noise; a uniform torque at ``random_rate``."""
    if rng.random() < random_rate:
        return rng.uniform(-2.0, 2.0, 1).astype(np.float32)
    cos, sin, velocity = observation
    if cos > 0.85:
        torque = -8.0 * np.arctan2(sin, cos) - 1.5 * velocity
    else:
        torque = 2.0 * np.sign(velocity or 1.0) * (velocity**2 / 6.0 + 5.0 * cos < 5.0)
    return np.clip([torque + rng.normal(0.0, 0.5)], -2.0, 2.0).astype(np.float32)


def mountaincar_action(observation: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    """Push along the velocity with ``strength``, N(0, 1) noise, clipped to [-1, 1]."""
    return np.clip([strength * np.sign(observation[1] or 1.0) + rng.normal(0.0, 1.0)], -1.0, 1.0).astype(np.float32)


def make_data(task: str, n_episodes: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The task's data: one row per step (``observations``, ``next_observations``, ``actions`` in the env's units,
    ``rewards``, ``terminations``, ``truncations``), and each episode's return and success."""
    env, rng = gym.make(TASKS[task]), np.random.default_rng(seed)
    rows: dict[str, list] = {key: [] for key in (*STEP_KEYS, "episode_returns", "episode_successes")}
    for episode in range(n_episodes):
        observation, _ = env.reset(seed=seed + episode)
        parameter = rng.uniform(0.4, 1.0) if task == "pendulum" else rng.uniform(0.0, 0.2)
        act = pendulum_action if task == "pendulum" else mountaincar_action
        done, total = False, 0.0
        while not done:
            action = act(observation, rng, parameter)
            next_observation, reward, terminated, truncated, _ = env.step(action)
            step = (observation, next_observation, action, reward, terminated, truncated)
            for key, value in zip(STEP_KEYS, step, strict=True):
                rows[key].append(value)
            observation, total, done = next_observation, total + reward, terminated or truncated
        rows["episode_returns"].append(total)
        rows["episode_successes"].append(bool(terminated))
    data = {key: np.asarray(values) for key, values in rows.items()}
    for key in ("observations", "next_observations", "actions", "rewards"):
        data[key] = data[key].astype(np.float32)
    return data


def replay_buffer(data: dict[str, np.ndarray], env: gym.Env) -> ReplayBuffer:
    """The data as SAC's rollouts would fill a buffer: actions scaled to [-1, 1], truncations as timeouts."""
    low, high = env.action_space.low, env.action_space.high
    buffer = ReplayBuffer(len(data["rewards"]), env.observation_space, env.action_space)
    for row in range(len(data["rewards"])):
        terminated, truncated = bool(data["terminations"][row]), bool(data["truncations"][row])
        buffer.add(data["observations"][row], data["next_observations"][row],
                   2.0 * (data["actions"][row] - low) / (high - low) - 1.0, np.array([data["rewards"][row]]),
                   np.array([terminated or truncated]), [{"TimeLimit.truncated": truncated and not terminated}])  # fmt: skip
    return buffer


def evaluate(model: CQL | IQL | BC, env_id: str, n_episodes: int) -> tuple[list[float], list[bool]]:
    env, returns, successes = gym.make(env_id), [], []
    for episode in range(n_episodes):
        observation, _ = env.reset(seed=EVAL_SEED + episode)
        done, total = False, 0.0
        while not done:
            action, _ = model.predict(observation, deterministic=True)
            observation, reward, terminated, truncated, _ = env.step(action)
            total, done = total + reward, terminated or truncated
        returns.append(float(total))
        successes.append(bool(terminated))
    return returns, successes


def run_ours(algorithm: str, data: dict[str, np.ndarray], env_id: str, seed: int, args: argparse.Namespace) -> dict:
    env = gym.make(env_id)
    model = {"cql": CQL, "iql": IQL, "bc": BC}[algorithm]("MlpPolicy", env, dataset=replay_buffer(data, env), seed=seed)
    start = time.perf_counter()
    model.learn(args.steps)
    seconds = time.perf_counter() - start
    returns, successes = evaluate(model, env_id, args.eval_episodes)
    return {"returns": returns, "successes": successes, "seconds": seconds}


def run_d3rlpy(algorithm: str, data_path: Path, seed: int, args: argparse.Namespace) -> dict:
    command = [args.d3rlpy_python, "-c", D3RLPY_SCRIPT, str(data_path), algorithm, str(seed), str(args.steps),
               str(args.eval_episodes), str(args.threads), str(EVAL_SEED)]  # fmt: skip
    output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def score(task: str, result: dict) -> float:
    return float(np.mean(result["successes"] if task == "mountaincar" else result["returns"]))


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--d3rlpy-python", default=None, help="a Python with d3rlpy 2.8.1 (none: ours only)")
    parser.add_argument("--tasks", nargs="+", choices=list(TASKS), default=list(TASKS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=10_000, help="gradient steps of each run (default 10,000)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes of data per task (default 100)")
    parser.add_argument("--eval-episodes", type=int, default=10, help="evaluation episodes per run (default 10)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of each run (default 1)")
    parser.add_argument("--output", default=None, help="JSON lines of every run (default: none)")
    parser.add_argument("--libraries", nargs="+", choices=["sb3-cql", "d3rlpy"], default=["sb3-cql", "d3rlpy"],
                        help="whose runs to make (default both; d3rlpy's need --d3rlpy-python)")  # fmt: skip
    args = parser.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    th.set_num_threads(args.threads)
    records = []
    if args.output and Path(args.output).exists():  # resume: runs already in the file are not run again
        records = [json.loads(line) for line in Path(args.output).read_text().splitlines() if line.strip()]
    done = {(r["task"], r["library"], r["algorithm"], r["seed"], r["steps"]) for r in records}
    with tempfile.TemporaryDirectory() as folder:
        for task in args.tasks:
            data = make_data(task, args.episodes)
            data_score = float(np.mean(data["episode_successes"] if task == "mountaincar" else data["episode_returns"]))
            print(f"{task}: data {data_score:.3f} ({len(data['rewards'])} transitions)", flush=True)
            data_path = Path(folder) / f"{task}.npz"
            np.savez(data_path, env_id=TASKS[task], **{k: v for k, v in data.items() if not k.startswith("episode_")})
            runs = [("sb3-cql", "cql"), ("sb3-cql", "iql"), ("sb3-cql", "bc")] if "sb3-cql" in args.libraries else []
            if args.d3rlpy_python and "d3rlpy" in args.libraries:
                runs += [("d3rlpy", "cql"), ("d3rlpy", "iql"), ("d3rlpy", "bc")]
            for library, algorithm in runs:
                for seed in args.seeds:
                    if (task, library, algorithm, seed, args.steps) in done:
                        continue
                    if library == "sb3-cql":
                        result = run_ours(algorithm, data, TASKS[task], seed, args)
                    else:
                        result = run_d3rlpy(algorithm, data_path, seed, args)
                    record = {"task": task, "library": library, "algorithm": algorithm, "seed": seed,
                              "steps": args.steps, "data": data_score, "score": score(task, result), **result}  # fmt: skip
                    records.append(record)
                    print(f"  {library} {algorithm} seed {seed}: {record['score']:.3f} ({result['seconds']:.0f} s)")
                    if args.output:
                        with open(args.output, "a") as file:
                            file.write(json.dumps(record) + "\n")
    print("\n| task | library | algorithm | mean over seeds | range | gradient steps/s |\n|---|---|---|---|---|---|")
    for task in args.tasks:
        for library, algorithm in sorted({(r["library"], r["algorithm"]) for r in records if r["task"] == task}):
            mine = [r for r in records if (r["task"], r["library"], r["algorithm"]) == (task, library, algorithm)]
            scores, speed = [r["score"] for r in mine], np.mean([r["steps"] / r["seconds"] for r in mine])
            spread = f"{min(scores):.3f} .. {max(scores):.3f}"
            print(f"| {task} | {library} | {algorithm} | {np.mean(scores):.3f} | {spread} | {speed:.0f} |")
    return records


if __name__ == "__main__":
    main(sys.argv[1:])
