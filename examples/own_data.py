"""Train CQL and BC on data of your own: numpy arrays, then a Minari dataset or an SB3 ReplayBuffer, then a model.

    python examples/own_data.py [--episodes 100] [--steps 10000] [--batch-size 256] [--eval-episodes 10]
                                [--data-dir DIR] [--seed 0]

The data are what a log of any controller holds, one row per step: ``observations``, ``next_observations`` (the
observation the step led to), ``actions`` in the env's own units, ``rewards``, ``terminations`` (the episode ended in
a terminal state: no value after it) and ``truncations`` (the episode was cut, by a time limit or the logger: the
state still had a future). Here they come from a noisy energy-pumping swing-up controller on Pendulum-v1, whose
episodes are all truncated at 200 steps.

The same arrays become a Minari dataset (``--data-dir``, by default a temporary folder, is Minari's
``MINARI_DATASETS_PATH``) and an SB3 ``ReplayBuffer``; CQL and BC train on each (``--steps`` gradient steps) and are
evaluated on the env (``--eval-episodes`` episodes). The documentation's *Bring your own data* page explains each
step.
"""

from __future__ import annotations

import argparse
import os
import tempfile

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

from sb3_cql import BC, CQL

ENV_ID = "Pendulum-v1"
DATA_KEYS = ("observations", "next_observations", "actions", "rewards", "terminations", "truncations")


def controller(observation: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The behaviour policy: pump energy until the pendulum swings up, hold it upright with a PD law, plus N(0, 0.5)
    torque noise; torques in the env's units, [-2, 2]."""
    cos, sin, velocity = observation
    angle = np.arctan2(sin, cos)
    if cos > 0.85:
        torque = -8.0 * angle - 1.5 * velocity
    else:
        energy = velocity**2 / 6.0 + 5.0 * cos  # 5 upright at rest (m = l = 1, g = 10)
        torque = 2.0 * np.sign(velocity or 1.0) * (energy < 5.0)
    return np.clip([torque + rng.normal(0.0, 0.5)], -2.0, 2.0).astype(np.float32)


def log_episodes(n_episodes: int, seed: int) -> dict[str, np.ndarray]:
    """The arrays a logger of the controller would hold: one row per step, episodes one after the other."""
    env, rng = gym.make(ENV_ID), np.random.default_rng(seed)
    rows: dict[str, list] = {key: [] for key in DATA_KEYS}
    for episode in range(n_episodes):
        observation, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            action = controller(observation, rng)
            next_observation, reward, terminated, truncated, _ = env.step(action)
            step = (observation, next_observation, action, reward, terminated, truncated)
            for key, value in zip(DATA_KEYS, step, strict=True):
                rows[key].append(value)
            observation, done = next_observation, terminated or truncated
    return {key: np.asarray(values) for key, values in rows.items()}


def episode_slices(data: dict[str, np.ndarray]) -> list[slice]:
    """Each episode's rows: an episode ends at a termination or a truncation."""
    ends = np.flatnonzero(data["terminations"] | data["truncations"]) + 1
    starts = np.concatenate([[0], ends[:-1]])
    return [slice(start, end) for start, end in zip(starts, ends, strict=True)]


def to_minari(data: dict[str, np.ndarray], dataset_id: str, env: gym.Env):
    """A Minari dataset of the arrays: one ``EpisodeBuffer`` per episode, its observations the episode's and then the
    last next observation (one more than its actions), actions in the env's units (CQL and BC scale them)."""
    import minari
    from minari.data_collector import EpisodeBuffer

    episodes = []
    for index, rows in enumerate(episode_slices(data)):
        observations = np.concatenate([data["observations"][rows], data["next_observations"][rows][-1:]])
        episodes.append(
            EpisodeBuffer(
                id=index,
                observations=observations.astype(np.float32),
                actions=data["actions"][rows].astype(np.float32),
                rewards=data["rewards"][rows].astype(np.float64),
                terminations=data["terminations"][rows].astype(bool),
                truncations=data["truncations"][rows].astype(bool),
            )
        )
    return minari.create_dataset_from_buffers(dataset_id, episodes, env=env, algorithm_name="noisy swing-up controller")


def scale_action(action: np.ndarray, action_space: spaces.Box) -> np.ndarray:
    """An action in the env's units scaled to [-1, 1], as SB3's ``policy.scale_action`` does before storing it."""
    return 2.0 * (action - action_space.low) / (action_space.high - action_space.low) - 1.0


def to_replay_buffer(data: dict[str, np.ndarray], env: gym.Env) -> ReplayBuffer:
    """An SB3 ``ReplayBuffer`` of the arrays, filled as SAC's ``collect_rollouts`` fills one: actions scaled to
    [-1, 1]; ``done`` is the end of an episode (termination or truncation) and ``infos[0]["TimeLimit.truncated"]``
    says it was a truncation (stored as ``timeouts``: SB3 bootstraps through it)."""
    buffer = ReplayBuffer(len(data["rewards"]), env.observation_space, env.action_space, handle_timeout_termination=True)
    for row in range(len(data["rewards"])):
        terminated, truncated = bool(data["terminations"][row]), bool(data["truncations"][row])
        buffer.add(
            data["observations"][row],
            data["next_observations"][row],
            scale_action(data["actions"][row], env.action_space),
            np.array([data["rewards"][row]]),
            np.array([terminated or truncated]),
            [{"TimeLimit.truncated": truncated and not terminated}],
        )
    return buffer


def main(argv: list[str] | None = None) -> dict[str, CQL | BC]:
    """Make the data, train CQL and BC on each form of it, print each model's mean return; return the models."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100, help="episodes of data (default 100, 20,000 transitions)")
    parser.add_argument("--steps", type=int, default=10_000, help="gradient steps of each model (default 10,000)")
    parser.add_argument("--batch-size", type=int, default=256, help="batch size of each gradient step (default 256)")
    parser.add_argument("--eval-episodes", type=int, default=10, help="evaluation episodes of each model (default 10)")
    parser.add_argument("--data-dir", default=None, help="Minari's datasets folder (default: a new temporary one)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    os.environ["MINARI_DATASETS_PATH"] = args.data_dir or tempfile.mkdtemp(prefix="own-data-")

    data = log_episodes(args.episodes, args.seed)
    returns = [data["rewards"][rows].sum() for rows in episode_slices(data)]
    print(f"data: {len(returns)} episodes, {len(data['rewards'])} transitions, mean return {np.mean(returns):.1f}")
    env = Monitor(gym.make(ENV_ID))
    dataset = to_minari(data, "own/Pendulum-v1/noisy-swing-up-v0", env)
    buffer = to_replay_buffer(data, env)

    models = {}
    for name, algorithm, source in [("CQL, Minari dataset", CQL, dataset), ("CQL, ReplayBuffer", CQL, buffer),
                                    ("BC, Minari dataset", BC, dataset), ("BC, ReplayBuffer", BC, buffer)]:  # fmt: skip
        model = algorithm("MlpPolicy", env, dataset=source, batch_size=args.batch_size, seed=args.seed).learn(args.steps)
        mean_return, _ = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes, deterministic=True)
        print(f"{name}: mean return {mean_return:.1f} over {args.eval_episodes} episodes", flush=True)
        models[name] = model
    return models


if __name__ == "__main__":
    main()
