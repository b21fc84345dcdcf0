"""Which perturbed physics defeat the PD controller on PandaPerturbed-v0.

    python benchmarks/perturbed_failures.py [--episodes 100]

Runs the PD controller for ``--episodes`` episodes (seeds 0..n-1) and compares each episode's object weight
(mass x |gravity|, N) with the Coulomb limit of the grip, 2 fingers x finger force x the object's friction.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import envs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100)
    args = parser.parse_args()
    env = gym.make("PandaPerturbed-v0")
    controller = envs.PDController.for_env(env)
    finger_force = env.unwrapped.config.finger_motor_force
    rows = []
    for seed in range(args.episodes):
        observation, physics = env.reset(seed=seed)
        done = False
        while not done:
            observation, _, terminated, truncated, info = env.step(controller.predict(observation)[0])
            done = terminated or truncated
        weight = physics["object_mass"] * abs(physics["gravity"])
        grip = 2 * finger_force * physics["object_lateral_friction"]
        rows.append(
            (physics["gravity"], physics["object_mass"], physics["object_lateral_friction"], weight > grip, info["is_success"])
        )
    table = np.array(rows, dtype=float)
    success, too_heavy = table[:, 4] == 1, table[:, 3] == 1
    print(f"success rate {success.mean():.2f} over {args.episodes} episodes")
    print(f"failures: {np.sum(~success)}, of which weight above the grip's Coulomb limit: {np.sum(~success & too_heavy)}")
    print(f"successes with weight above that limit: {np.sum(success & too_heavy)}")
    print(f"failures with gravity above -1 m/s^2: {np.sum(~success & (table[:, 0] > -1))}")
    for gravity, mass, friction, _, ok in rows:
        if not ok:
            print(f"  failed: gravity {gravity:6.1f} m/s^2, mass {mass:5.2f} kg, friction {friction:.2f}")


if __name__ == "__main__":
    main()
