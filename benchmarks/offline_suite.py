"""Our CQL, IQL and BC beside d3rlpy's, each at its defaults, on a suite of small offline data sets of varied behaviour.

    python benchmarks/offline_suite.py OUT [--d3rlpy-python V/bin/python] [--datasets NAME ...] [--seeds 0 1]
        [--algorithms cql iql bc] [--libraries sb3-cql d3rlpy] [--steps 10000] [--eval-episodes 20]
        [--variant LABEL=JSON] [--source buffer|minari] [--lane I/N] [--threads 1] [--table [--per-seed]]

The data sets, made here by seeded scripts in seconds (the online learner's in a few minutes) and kept in
``OUT/data/NAME.npz``, are the same arrays for both libraries, and each run is scored against its own data:

====================  =============================  ======  ===================================================
name                  task                           reward  behaviour
====================  =============================  ======  ===================================================
mountaincar-weak      MountainCarContinuous-v0       sparse  100 episodes of a push along the velocity of a
                                                             strength drawn per episode from U(0, 0.2), plus N(0, 1)
mountaincar-mixture   MountainCarContinuous-v0       sparse  200 episodes: two thirds pure N(0, 1) action noise,
                                                             one third a bang-bang energy pump with N(0, 0.2) noise
pendulum-medium       Pendulum-v1                    dense   100 episodes of a swing-up and PD hold with N(0, 0.5)
                                                             noise and a uniform torque at a rate drawn per episode
                                                             from U(0.4, 1)
pendulum-mixture      Pendulum-v1                    dense   100 episodes: half the swing-up with N(0, 0.2) noise,
                                                             half uniform random torques
pendulum-replay       Pendulum-v1                    dense   the first 6,000 env steps (30 episodes) of SB3's SAC
                                                             learning online, seed 0
lunar-noisy           LunarLanderContinuous-v3       dense   100 episodes of gymnasium's landing heuristic with
                                                             N(0, s) noise, s drawn per episode from U(0.1, 1)
lunar-mixture         LunarLanderContinuous-v3       dense   100 episodes: half the heuristic with N(0, 0.1)
                                                             noise, half uniform random actions
====================  =============================  ======  ===================================================

MountainCarContinuous-v0 is scored by the success rate (the episode terminated at the flag), the others by the mean
return. The three tasks' observations lie on scales far apart (a velocity of 0.07 against one of 8; the lander's
eight coordinates and its two leg contacts), the reason the observation scaling is one of the defaults the suite
weighs. LunarLanderContinuous-v3 needs Box2D (``pip install "gymnasium[box2d]"``).

Ours train from an SB3 ``ReplayBuffer`` (``dataset=``, actions scaled to [-1, 1], truncations as timeouts) with every
constructor keyword at its default, or at the defaults changed by ``--variant LABEL=JSON`` (keywords, e.g.
``raw='{"normalize_observations": false}'``, recorded under the label). d3rlpy's (``CQLConfig()``, ``IQLConfig()``,
``BCConfig()``) train from an ``MDPDataset`` of the same arrays with their defaults, plus the ``MinMaxActionScaler`` of
the env's action bounds that their tanh policies need, in the interpreter given by ``--d3rlpy-python`` (d3rlpy pins
gymnasium 1.0.0: ``python -m venv V && V/bin/pip install torch==2.13.0 d3rlpy==2.8.1``, and for ``--source minari`` also
``"minari[hdf5]==0.5.4" pillow``); their policy comes back as
TorchScript (with its scalers) and acts here, so both libraries meet the same env and the same evaluation: the last
policy's deterministic action in ``--eval-episodes`` episodes on env seeds 10000 onwards (the data's are 0 onwards).

``--source minari`` gives both libraries the same arrays as Minari datasets (``OUT/minari``, Minari's datasets
path; ids ``offline-suite/NAME-v0``): ours get the ``MinariDataset`` as ``dataset=``, d3rlpy's an ``MDPDataset`` of
its episodes, so a user with a Minari dataset meets the same defaults; the rows are labelled ``minari``.

Each run is one file, ``OUT/runs/DATASET-LIBRARY-ALGORITHM[-LABEL]-seedS.json``, written whole or not at all: the same
command skips the runs already there, so a killed suite resumes by run. ``--lane I/N`` takes every N-th run from
the I-th (0-based), one lane a core. Our trained models are kept beside the records, in ``OUT/models``. ``--table``
prints the table of the runs in ``OUT`` (mean and range over seeds).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer

EVAL_SEED = 10_000
STEP_KEYS = ("observations", "next_observations", "actions", "rewards", "terminations", "truncations")
ALGORITHMS = ("cql", "iql", "bc")

# Train with d3rlpy's defaults, export the policy (its observation and action scalers inside) as TorchScript, and check
# that the export acts as d3rlpy's own predict does on the data's observations.
D3RLPY_SCRIPT = r"""
import json, sys, time
import numpy as np, torch, d3rlpy
data_path, algo_name, seed, steps, threads, policy_path = sys.argv[1:7]
torch.set_num_threads(int(threads))
d3rlpy.seed(int(seed))
if data_path.startswith("minari:"):  # the same arrays, read back from the Minari dataset's episodes
    import minari
    source = minari.load_dataset(data_path[len("minari:"):])
    episodes = list(source.iterate_episodes())
    data = {key: np.concatenate([getattr(e, key) for e in episodes])
            for key in ("actions", "rewards", "terminations", "truncations")}
    data["observations"] = np.concatenate([e.observations[:-1] for e in episodes]).astype(np.float32)
    data["action_low"], data["action_high"] = source.action_space.low, source.action_space.high
else:
    data = dict(np.load(data_path))
dataset = d3rlpy.dataset.MDPDataset(data["observations"], data["actions"], data["rewards"], data["terminations"],
                                    timeouts=data["truncations"])
scaler = d3rlpy.preprocessing.MinMaxActionScaler(minimum=data["action_low"], maximum=data["action_high"])
config = {"cql": d3rlpy.algos.CQLConfig, "iql": d3rlpy.algos.IQLConfig, "bc": d3rlpy.algos.BCConfig}[algo_name]
algo = config(action_scaler=scaler).create(device="cpu:0")
start = time.perf_counter()
algo.fit(dataset, n_steps=int(steps), n_steps_per_epoch=int(steps), show_progress=False, save_interval=10**9,
         logger_adapter=d3rlpy.logging.NoopAdapterFactory())
seconds = time.perf_counter() - start
algo.save_policy(policy_path)
observations = data["observations"][:256]
exported = torch.jit.load(policy_path)(torch.as_tensor(observations)).detach().numpy()
gap = float(np.abs(exported - algo.predict(observations)).max())
print(json.dumps({"seconds": seconds, "export_gap": gap}))
"""


@dataclass(frozen=True)
class Task:
    env_id: str
    scored_by: str  # "success" or "return"


TASKS = {
    "mountaincar": Task("MountainCarContinuous-v0", "success"),
    "pendulum": Task("Pendulum-v1", "return"),
    "lunar": Task("LunarLanderContinuous-v3", "return"),
}


# Behaviour: each takes the env, the data's generator and the episode's index, and returns the episode's policy.
def pendulum_swing_up(rng: np.random.Generator, noise: float, random_rate: float) -> Callable:
    """Swing up by pumping energy, hold upright with a PD law, N(0, ``noise``); a uniform torque at ``random_rate``."""

    def act(observation: np.ndarray, env: gym.Env) -> np.ndarray:
        if rng.random() < random_rate:
            return rng.uniform(-2.0, 2.0, 1).astype(np.float32)
        cos, sin, velocity = observation
        if cos > 0.85:
            torque = -8.0 * np.arctan2(sin, cos) - 1.5 * velocity
        else:
            torque = 2.0 * np.sign(velocity or 1.0) * (velocity**2 / 6.0 + 5.0 * cos < 5.0)
        return np.clip([torque + rng.normal(0.0, noise)], -2.0, 2.0).astype(np.float32)

    return act


def mountaincar_push(rng: np.random.Generator, strength: float, noise: float) -> Callable:
    """Push along the velocity with ``strength``, N(0, ``noise``), clipped to [-1, 1]."""

    def act(observation: np.ndarray, env: gym.Env) -> np.ndarray:
        push = strength * np.sign(observation[1] or 1.0) + rng.normal(0.0, noise)
        return np.clip([push], -1.0, 1.0).astype(np.float32)

    return act


def lunar_heuristic(rng: np.random.Generator, noise: float) -> Callable:
    """Gymnasium's landing heuristic, N(0, ``noise``) on both engines, clipped to [-1, 1]."""
    from gymnasium.envs.box2d.lunar_lander import heuristic

    def act(observation: np.ndarray, env: gym.Env) -> np.ndarray:
        action = heuristic(env.unwrapped, observation) + rng.normal(0.0, noise, 2)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    return act


def uniform(rng: np.random.Generator) -> Callable:
    def act(observation: np.ndarray, env: gym.Env) -> np.ndarray:
        return rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32)

    return act


def mixture(good: Callable, share: float) -> Callable:
    """``good(rng)`` in a ``share`` of the episodes (drawn per episode), uniform random actions in the others."""
    return lambda rng, episode: good(rng) if rng.random() < share else uniform(rng)


BEHAVIOURS: dict[str, tuple[str, int, Callable]] = {  # name: (task, episodes, episode -> policy)
    "mountaincar-weak": ("mountaincar", 100, lambda rng, e: mountaincar_push(rng, rng.uniform(0.0, 0.2), 1.0)),
    "mountaincar-mixture": (
        "mountaincar",
        200,
        lambda rng, e: mountaincar_push(rng, 1.0, 0.2) if rng.random() < 1 / 3 else mountaincar_push(rng, 0.0, 1.0),
    ),
    "pendulum-medium": ("pendulum", 100, lambda rng, e: pendulum_swing_up(rng, 0.5, rng.uniform(0.4, 1.0))),
    "pendulum-mixture": ("pendulum", 100, mixture(lambda rng: pendulum_swing_up(rng, 0.2, 0.0), 0.5)),
    "lunar-noisy": ("lunar", 100, lambda rng, e: lunar_heuristic(rng, rng.uniform(0.1, 1.0))),
    "lunar-mixture": ("lunar", 100, mixture(lambda rng: lunar_heuristic(rng, 0.1), 0.5)),
}
DATASETS = [*BEHAVIOURS, "pendulum-replay"]


def task_of(name: str) -> Task:
    return TASKS[name.split("-")[0]]


def rollouts(name: str, seed: int = 0) -> dict[str, np.ndarray]:
    """A scripted behaviour's data: one row per step (``observations``, ``next_observations``, ``actions`` in the
    env's units, ``rewards``, ``terminations``, ``truncations``), and each episode's return and success."""
    task_name, n_episodes, behaviour = BEHAVIOURS[name]
    env, rng = gym.make(TASKS[task_name].env_id), np.random.default_rng(seed)
    rows: dict[str, list] = {key: [] for key in (*STEP_KEYS, "episode_returns", "episode_successes")}
    for episode in range(n_episodes):
        observation, _ = env.reset(seed=seed + episode)
        act = behaviour(rng, episode)
        done, total = False, 0.0
        while not done:
            action = act(observation, env)
            next_observation, reward, terminated, truncated, _ = env.step(action)
            step = (observation, next_observation, action, reward, terminated, truncated)
            for key, value in zip(STEP_KEYS, step, strict=True):
                rows[key].append(value)
            observation, total, done = next_observation, total + reward, terminated or truncated
        rows["episode_returns"].append(total)
        rows["episode_successes"].append(bool(terminated))
    return {key: np.asarray(values) for key, values in rows.items()}


def online_learner_replay(seed: int = 0, steps: int = 6_000) -> dict[str, np.ndarray]:
    """The first ``steps`` env steps of SB3's SAC learning Pendulum-v1 online, in the order it took them."""
    from stable_baselines3 import SAC

    env = gym.make("Pendulum-v1")
    model = SAC("MlpPolicy", env, seed=seed, learning_starts=1_000, device="cpu").learn(steps)
    buffer, n = model.replay_buffer, model.replay_buffer.pos
    timeouts = buffer.timeouts[:n, 0].astype(bool)
    data = {
        "observations": buffer.observations[:n, 0],
        "next_observations": buffer.next_observations[:n, 0],
        "actions": model.policy.unscale_action(buffer.actions[:n, 0]),
        "rewards": buffer.rewards[:n, 0],
        "terminations": buffer.dones[:n, 0].astype(bool) & ~timeouts,
        "truncations": timeouts,
    }
    ends = np.flatnonzero(data["terminations"] | data["truncations"]) + 1
    data["episode_returns"] = np.array([chunk.sum() for chunk in np.split(data["rewards"], ends)[: len(ends)]])
    data["episode_successes"] = data["terminations"][ends - 1]
    return data


def make_data(name: str, seed: int = 0) -> dict[str, np.ndarray]:
    data = online_learner_replay(seed) if name == "pendulum-replay" else rollouts(name, seed)
    for key in ("observations", "next_observations", "actions", "rewards"):
        data[key] = np.asarray(data[key], dtype=np.float32)
    return data


def load_data(name: str, folder: Path) -> dict[str, np.ndarray]:
    """The data set from ``folder/NAME.npz``, made and written there (atomically) the first time."""
    path = folder / f"{name}.npz"
    if not path.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        data, space = make_data(name), gym.make(task_of(name).env_id).action_space
        with tempfile.NamedTemporaryFile(dir=folder, suffix=".npz", delete=False) as file:
            np.savez(file, action_low=space.low, action_high=space.high, **data)
        os.replace(file.name, path)
    with np.load(path) as stored:
        return dict(stored)


def data_score(name: str, data: dict[str, np.ndarray]) -> float:
    key = "episode_successes" if task_of(name).scored_by == "success" else "episode_returns"
    return float(np.mean(data[key]))


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


def evaluate(act: Callable[[np.ndarray], np.ndarray], env_id: str, n_episodes: int) -> tuple[list[float], list[bool]]:
    """``act``'s returns and successes in ``n_episodes`` episodes on env seeds ``EVAL_SEED`` onwards."""
    env, returns, successes = gym.make(env_id), [], []
    for episode in range(n_episodes):
        observation, _ = env.reset(seed=EVAL_SEED + episode)
        done, total = False, 0.0
        while not done:
            observation, reward, terminated, truncated, _ = env.step(act(observation))
            total, done = total + reward, terminated or truncated
        returns.append(float(total))
        successes.append(bool(terminated))
    return returns, successes


def minari_id(name: str) -> str:
    return f"offline-suite/{name}-v0"


def write_minari(name: str, data: dict[str, np.ndarray], folder: Path) -> None:
    """The data set as a Minari dataset under ``folder`` (Minari's datasets path): one episode a run of rows ending in
    a termination or a truncation, its observations the episode's and then the last next observation. Made in a
    folder beside it and moved in whole."""
    import minari
    from minari.data_collector import EpisodeBuffer

    target = folder / minari_id(name)
    if target.is_dir():
        return
    ends = np.flatnonzero(data["terminations"] | data["truncations"]) + 1
    episodes = []
    for index, (start, end) in enumerate(zip(np.concatenate([[0], ends[:-1]]), ends, strict=True)):
        rows = slice(start, end)
        observations = np.concatenate([data["observations"][rows], data["next_observations"][rows][-1:]])
        episode = {key: data[key][rows] for key in ("actions", "terminations", "truncations")}
        episodes.append(EpisodeBuffer(id=index, observations=observations, rewards=data["rewards"][rows].astype(np.float64),
                                      **episode))  # fmt: skip
    staging = Path(tempfile.mkdtemp(dir=folder.parent, prefix="minari-staging-"))
    os.environ["MINARI_DATASETS_PATH"] = str(staging)
    try:
        minari.create_dataset_from_buffers(minari_id(name), episodes, env=gym.make(task_of(name).env_id))
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(staging / minari_id(name), target)
    finally:
        os.environ["MINARI_DATASETS_PATH"] = str(folder)
        shutil.rmtree(staging, ignore_errors=True)


def our_dataset(name: str, data: dict[str, np.ndarray], env: gym.Env, minari_folder: Path | None):
    """What our algorithms' ``dataset=`` gets: an SB3 ``ReplayBuffer``, or with a Minari folder the Minari dataset."""
    if minari_folder is None:
        return replay_buffer(data, env)
    import minari

    os.environ["MINARI_DATASETS_PATH"] = str(minari_folder)
    return minari.load_dataset(minari_id(name))


def run_ours(algorithm: str, name: str, data: dict, seed: int, keywords: dict, args: argparse.Namespace) -> dict:
    from sb3_cql import BC, CQL, IQL

    env_id = task_of(name).env_id
    env = gym.make(env_id)
    model_class = {"cql": CQL, "iql": IQL, "bc": BC}[algorithm]
    dataset = our_dataset(name, data, env, args.out / "minari" if args.source == "minari" else None)
    model = model_class("MlpPolicy", env, dataset=dataset, seed=seed, **keywords)
    start = time.perf_counter()
    model.learn(args.steps)
    seconds = time.perf_counter() - start
    returns, successes = evaluate(lambda o: model.predict(o, deterministic=True)[0], env_id, args.eval_episodes)
    return {"returns": returns, "successes": successes, "seconds": seconds, "model": model}


def run_d3rlpy(algorithm: str, name: str, seed: int, args: argparse.Namespace) -> dict:
    env_id = task_of(name).env_id
    data_path = f"minari:{minari_id(name)}" if args.source == "minari" else str(args.out / "data" / f"{name}.npz")
    with tempfile.TemporaryDirectory() as folder:
        policy_path = Path(folder) / "policy.pt"
        command = [args.d3rlpy_python, "-c", D3RLPY_SCRIPT, data_path, algorithm, str(seed), str(args.steps),
                   str(args.threads), str(policy_path)]  # fmt: skip
        environment = {**os.environ, "MINARI_DATASETS_PATH": str(args.out / "minari")}
        finished = subprocess.run(command, capture_output=True, text=True, env=environment)
        if finished.returncode:
            log = args.out / "logs" / f"{run_name(name, 'd3rlpy', algorithm, None, seed)}.log"
            write_text(log, finished.stderr)
            last = (finished.stderr.strip().splitlines() or ["no message"])[-1]
            raise RunFailed(f"d3rlpy's {algorithm} on {name}, seed {seed}, failed in {args.d3rlpy_python}: {last} "
                            f"(its whole stderr: {log})")  # fmt: skip
        result = json.loads(finished.stdout.strip().splitlines()[-1])
        policy = th.jit.load(str(policy_path))

        def act(observation: np.ndarray) -> np.ndarray:
            with th.no_grad():
                return policy(th.as_tensor(observation[None], dtype=th.float32))[0].numpy()

        returns, successes = evaluate(act, env_id, args.eval_episodes)
    return {"returns": returns, "successes": successes, **result}


def run_name(dataset: str, library: str, algorithm: str, label: str | None, seed: int) -> str:
    return f"{dataset}-{library}-{algorithm}{f'-{label}' if label else ''}-seed{seed}"


class RunFailed(Exception):
    """A run that could not finish, with the one line that says why."""


def write_json(path: Path, record: dict) -> None:
    write_text(path, json.dumps(record))


def write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=path.suffix, delete=False) as file:
        file.write(text)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(file.name, 0o666 & ~umask)  # a file's usual mode, not the temporary file's owner-only one
    os.replace(file.name, path)


def d3rlpy_import_error(python: str, minari: bool) -> str | None:
    """Why ``python`` cannot run d3rlpy's side of the suite (d3rlpy, and with the Minari source Minari's HDF5 storage),
    or ``None``."""
    imports = "import d3rlpy" + ("; import minari.dataset._storages.hdf5_storage" if minari else "")
    try:
        finished = subprocess.run([python, "-c", imports], capture_output=True, text=True)
    except OSError as error:
        return f"{python} cannot be run ({error.strerror})"
    if finished.returncode:
        return f"{python}: {(finished.stderr.strip().splitlines() or ['no message'])[-1]}"
    return None


def table(out: Path, per_seed: bool = False) -> str:
    """Mean (and range) over seeds of every row in ``OUT/runs``, a column per data set; with ``per_seed`` each seed's
    score instead, in the order of the data set's seeds (``0.50 / 0.55``, a dash for a seed the row lacks)."""
    records = [json.loads(path.read_text()) for path in sorted((out / "runs").glob("*.json"))]
    datasets = [name for name in DATASETS if any(r["dataset"] == name for r in records)]
    rows = sorted({(r["library"], r["algorithm"], r.get("label") or "") for r in records})
    lines = ["| | " + " | ".join(datasets) + " |", "|---" * (len(datasets) + 1) + "|"]
    scores = {d: next(r["data"] for r in records if r["dataset"] == d) for d in datasets}
    lines.append("| the data | " + " | ".join(f"{scores[d]:.2f}" for d in datasets) + " |")
    for library, algorithm, label in rows:
        cells = []
        for dataset in datasets:
            by_seed = {r["seed"]: r["score"] for r in records if (r["dataset"], r["library"], r["algorithm"],
                       r.get("label") or "") == (dataset, library, algorithm, label)}  # fmt: skip
            mine = list(by_seed.values())
            if per_seed:  # a dash where a seed another row of the data set has is missing
                digits = 2 if task_of(dataset).scored_by == "success" else 1
                seeds = sorted({r["seed"] for r in records if r["dataset"] == dataset})
                scores = [f"{by_seed[seed]:.{digits}f}" if seed in by_seed else "-" for seed in seeds]
                cells.append(" / ".join(scores) if by_seed else "")
            else:
                cells.append(f"{np.mean(mine):.2f} ({min(mine):.2f}..{max(mine):.2f}, {len(mine)})" if mine else "")
        name = f"{'our' if library == 'sb3-cql' else 'd3rlpy'} {algorithm.upper()}{f' {label}' if label else ''}"
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="folder of the data sets and of one JSON file a run")
    parser.add_argument("--d3rlpy-python", default=None, help="a Python with d3rlpy 2.8.1 (none: ours only)")
    parser.add_argument("--datasets", nargs="+", choices=DATASETS, default=DATASETS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--algorithms", nargs="+", choices=ALGORITHMS, default=list(ALGORITHMS))
    parser.add_argument("--libraries", nargs="+", choices=["sb3-cql", "d3rlpy"], default=["sb3-cql", "d3rlpy"])
    parser.add_argument("--steps", type=int, default=10_000, help="gradient steps of each run (default 10,000)")
    parser.add_argument("--eval-episodes", type=int, default=20, help="evaluation episodes per run (default 20)")
    parser.add_argument("--variant", default=None, metavar="LABEL=JSON", help="our keywords, recorded under LABEL")
    parser.add_argument("--lane", default="0/1", metavar="I/N", help="every N-th run from the I-th (default 0/1)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of each run (default 1)")
    parser.add_argument("--source", choices=["buffer", "minari"], default="buffer",
                        help="the data as an SB3 ReplayBuffer (default) or a Minari dataset, for both libraries")  # fmt: skip
    parser.add_argument("--table", action="store_true", help="print the table of the runs in OUT and stop")
    parser.add_argument("--per-seed", action="store_true", help="with --table, each seed's score, not their mean")
    args = parser.parse_args(argv)
    if args.per_seed and not args.table:
        parser.error("--per-seed: a form of --table, given without it")
    if args.table:
        print(table(args.out, per_seed=args.per_seed))
        return 0
    label, keywords = None, {}
    if args.variant:
        label, _, text = args.variant.partition("=")
        try:
            keywords = json.loads(text)
        except json.JSONDecodeError as error:
            parser.error(f"--variant {args.variant!r}: JSON after '=' expected ({error})")
        if not label.isidentifier() or not isinstance(keywords, dict):
            example = "raw='{\"normalize_observations\": false}'"
            parser.error(f"--variant {args.variant!r}: LABEL=JSON of keywords expected, e.g. {example}")
        from sb3_cql import BC, CQL, IQL
        from sb3_cql.common import KeywordError

        for algorithm in args.algorithms:  # before any data are made or run trained
            try:
                {"cql": CQL, "iql": IQL, "bc": BC}[algorithm].refuse_unknown_keywords(keywords)
            except KeywordError as error:
                parser.error(f"--variant {args.variant!r}: {error}")
    lane, _, lanes = args.lane.partition("/")
    if not (lane.isdigit() and lanes.isdigit() and int(lane) < int(lanes)):
        parser.error(f"--lane {args.lane!r}: I/N with 0 <= I < N expected, e.g. 0/2")
    for env_id in sorted({task_of(name).env_id for name in args.datasets}):  # a missing simulator: one line, up front
        try:
            gym.make(env_id).close()
        except gym.error.DependencyNotInstalled as error:
            parser.error(f"--datasets: {env_id} cannot be made here: {error}")
    libraries = [name for name in args.libraries if name == "sb3-cql" or args.d3rlpy_python]
    if args.variant:
        libraries = ["sb3-cql"]
    if "d3rlpy" in libraries and (error := d3rlpy_import_error(args.d3rlpy_python, args.source == "minari")):
        parser.error(f'--d3rlpy-python {error} (it needs torch==2.13.0 d3rlpy==2.8.1 "minari[hdf5]==0.5.4" pillow)')
    if args.source == "minari":  # a row of its own: the label names the source
        label = f"{label}+minari" if label else "minari"
    sys.stdout.reconfigure(line_buffering=True)
    th.set_num_threads(args.threads)
    runs = [(dataset, library, algorithm, seed) for seed in args.seeds for dataset in args.datasets
            for algorithm in args.algorithms for library in libraries]  # fmt: skip
    for index, (dataset, library, algorithm, seed) in enumerate(runs):
        path = args.out / "runs" / f"{run_name(dataset, library, algorithm, label, seed)}.json"
        if index % int(lanes) != int(lane) or path.exists():
            continue
        data = load_data(dataset, args.out / "data")
        if args.source == "minari":
            write_minari(dataset, data, args.out / "minari")
        if library == "sb3-cql":
            result = run_ours(algorithm, dataset, data, seed, keywords, args)
            result.pop("model").save(args.out / "models" / f"{path.stem}.zip")  # whole or not at all, as ours save
        else:
            try:
                result = run_d3rlpy(algorithm, dataset, seed, args)
            except RunFailed as error:
                print(f"offline_suite.py: error: {error}", file=sys.stderr)
                return 1
        scored = result["successes"] if task_of(dataset).scored_by == "success" else result["returns"]
        record = {"dataset": dataset, "library": library, "algorithm": algorithm, "label": label, "keywords": keywords,
                  "source": args.source,
                  "seed": seed, "steps": args.steps, "data": data_score(dataset, data), "score": float(np.mean(scored)),
                  "date": time.strftime("%Y-%m-%d"), **result}  # fmt: skip
        write_json(path, record)
        print(f"{path.stem}: {record['score']:.3f} (data {record['data']:.3f}; {result['seconds']:.0f} s)")
    print(table(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
