"""Env steps/s of each task next to the raw speed of the same PyBullet scene, measured in one run.

    python benchmarks/env_speed.py [--steps 2000] [--rounds 5]

For every task, three loops alternate for ``--rounds`` rounds and the median of each is reported:

- raw: the env's own client driven directly, one ``setJointMotorControl2`` per joint with the action's
  target (the env's forces and velocity limits) and one ``stepSimulation`` (same time step and substeps)
  per step, and the scene reset where the env's time limit resets it (random actions never succeed);
- env: ``env.step`` with the same actions (absolute mode: target clipping, NaN checks, observation,
  success check and the force/perturbation logic included);
- pd: ``env.step`` driven by the PD controller, whose inverse kinematics is included in the time.

The ratio env/raw is the env's overhead; the goal is >= 0.8.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import gymnasium as gym
import numpy as np
import pybullet

import envs
from envs.robot import JOINTS


def time_raw(env: gym.Env, actions: np.ndarray, seed: int) -> float:
    unwrapped = env.unwrapped
    env.reset(seed=seed)
    robot, client = unwrapped.robot, unwrapped.sim.id
    motors = list(zip(JOINTS, robot.motor_forces, robot.max_velocities, strict=True))
    start = time.perf_counter()
    for step, action in enumerate(actions, start=1):
        # The same motor commands as the env's (PyBullet has no array call taking velocity limits).
        for (joint, force, max_velocity), target in zip(motors, action.tolist(), strict=True):
            pybullet.setJointMotorControl2(
                robot.body, joint, pybullet.POSITION_CONTROL, targetPosition=target, force=force,
                maxVelocity=max_velocity, physicsClientId=client,
            )  # fmt: skip
        pybullet.stepSimulation(physicsClientId=client)
        if step % envs.MAX_EPISODE_STEPS == 0:  # where the env's time limit resets it: the same physics
            env.reset()
    return len(actions) / (time.perf_counter() - start)


def time_env(env: gym.Env, actions: np.ndarray, seed: int) -> float:
    env.reset(seed=seed)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return len(actions) / (time.perf_counter() - start)


def time_pd(env: gym.Env, controller: envs.PDController, n_steps: int, seed: int) -> float:
    observation, _ = env.reset(seed=seed)
    start = time.perf_counter()
    for _ in range(n_steps):
        action, _ = controller.predict(observation)
        observation, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            observation, _ = env.reset()
    return n_steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000, help="steps per loop and round")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    machine = platform.processor() or platform.machine()
    print(f"# {machine}, Python {platform.python_version()}, pybullet API {pybullet.getAPIVersion()}")
    print(f"# {args.rounds} rounds of {args.steps} steps, medians; one process, one core")
    print(f"{'env':<20}{'raw steps/s':>12}{'env steps/s':>12}{'env/raw':>9}{'PD steps/s':>12}")
    for env_id in envs.ENV_IDS:
        env = gym.make(env_id)
        controller = envs.PDController.for_env(env)
        actions = np.random.default_rng(0).uniform(env.action_space.low, env.action_space.high, (args.steps, 9))
        raw, stepped, pd = [], [], []
        for round_ in range(args.rounds):
            raw.append(time_raw(env, actions, seed=round_))
            stepped.append(time_env(env, actions, seed=round_))
            pd.append(time_pd(env, controller, args.steps, seed=round_))
        raw_rate, env_rate, pd_rate = (statistics.median(values) for values in (raw, stepped, pd))
        print(f"{env_id:<20}{raw_rate:>12.0f}{env_rate:>12.0f}{env_rate / raw_rate:>9.2f}{pd_rate:>12.0f}", flush=True)
        env.close()
        controller.close()


if __name__ == "__main__":
    main()
