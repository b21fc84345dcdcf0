"""A trained BC actor continued with BC at a small constant rate: success (10 episodes, env seed 1000) every K steps.

Usage: python results/diagnostics/bc_continued.py BC_MODEL.zip STEPS K LR BATCH DATASET_ID
"""

import sys

import gymnasium as gym
import torch as th
from stable_baselines3.common.logger import configure

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import BC
from sb3_cql.evaluate import success_rate

th.set_num_threads(1)
bc_path, steps, every, lr, batch, dataset = (
    sys.argv[1],
    int(sys.argv[2]),
    int(sys.argv[3]),
    float(sys.argv[4]),
    int(sys.argv[5]),
    sys.argv[6],
)
env_kwargs = {"action_mode": "delta"}
env = gym.make("Panda-v0", **env_kwargs)
old = BC.load(bc_path)
model = BC(
    "MlpPolicy", env, dataset=dataset, learning_rate=lr, batch_size=batch, policy_kwargs=dict(net_arch=[256, 256, 256]), seed=1
)
model.actor.load_state_dict(old.actor.state_dict())
model.set_logger(configure(None, ["csv"]))


def ev():
    return success_rate(model, "Panda-v0", n_episodes=10, seed=1000, env_kwargs=env_kwargs)


print(0, ev(), flush=True)
done = 0
while done < steps:
    model.learn(every, reset_num_timesteps=False, log_interval=every)
    done += every
    print(done, ev(), flush=True)
