"""Which action dimensions move when CQL's actor starts following Q, and the critic's dQ/da at the clone's actions.

Usage: python results/diagnostics/action_drift.py BC_MODEL.zip
"""

import sys

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.logger import configure

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import BC, CQL

th.set_num_threads(1)
bc = BC.load(sys.argv[1])
env = gym.make("Panda-v0", action_mode="delta")
model = CQL(
    "MlpPolicy",
    env,
    dataset="sb3cql/Panda-v0/noisy-delta-v0",
    policy_kwargs=dict(net_arch=[256, 256, 256]),
    seed=1,
    batch_size=128,
    bc_steps=3000,
    reward_scale=4.0,
    reward_bias=-2.0,
)
model.actor.load_state_dict(bc.actor.state_dict())
model.set_logger(configure(None, ["csv"]))
probe = model.replay_buffer.sample(4000)


def actions():
    with th.no_grad():
        return model.actor(probe.observations, deterministic=True).numpy()


def qgrad():
    a = th.tensor(actions(), requires_grad=True)
    q = th.cat(model.critic(probe.observations, a), 1).min(1).values.sum()
    (g,) = th.autograd.grad(q, a)
    return g.mean(0).numpy(), g.abs().mean(0).numpy()


model.learn(3000)
a0 = actions()
print("dQ/da mean, |dQ/da| mean at 3000:", *[np.round(x, 3).tolist() for x in qgrad()], flush=True)
for k in range(4):
    model.learn(250, reset_num_timesteps=False)
    a = actions()
    print(
        3000 + 250 * (k + 1),
        "mean shift per dim",
        np.round((a - a0).mean(0), 3).tolist(),
        "mean |shift|",
        np.round(np.abs(a - a0).mean(0), 3).tolist(),
        flush=True,
    )
print("dQ/da after:", *[np.round(x, 3).tolist() for x in qgrad()], flush=True)
