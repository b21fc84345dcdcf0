"""Train CQL briefly on x-noisy-delta-v0, then compare its Q at data actions, perturbed data actions and policy actions.

Usage: python results/diagnostics/q_probe.py STEPS '{"batch_size": 128, "bc_steps": 10000, ...}'
"""

import json
import sys

import gymnasium as gym
import torch as th
from stable_baselines3.common.logger import configure

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL

th.set_num_threads(1)
steps, kwargs = int(sys.argv[1]), json.loads(sys.argv[2])
env = gym.make("Panda-v0", action_mode="delta")
model = CQL(
    "MlpPolicy",
    env,
    dataset="sb3cql/Panda-v0/x-noisy-delta-v0",
    policy_kwargs=dict(net_arch=[256, 256, 256]),
    seed=1,
    **kwargs,
)
model.set_logger(configure(None, ["csv"]))
model.learn(steps)
data = model.replay_buffer.sample(2000)


def q(actions):
    with th.no_grad():
        return th.cat(model.critic(data.observations, actions), 1).min(1).values.mean().item()


a = data.actions
print("gripper data values", a[:, -2:].unique()[:10].tolist())
print("Q data", q(a))
for v in (0.99, 0.97, 0.9, 0.5):
    b = a.clone()
    b[:, -2:] = b[:, -2:] * v
    print("Q gripper x", v, q(b))
b = a.clone()
b[:, :-2] += 0.05 * th.randn_like(b[:, :-2])
print("Q arm +N(0,0.05)", q(b.clamp(-1, 1)))
with th.no_grad():
    mean, log_std, _ = model.actor.get_action_dist_params(data.observations)
    pi, _ = model.actor.action_log_prob(data.observations)
print("Q policy mean", q(th.tanh(mean)), "Q policy sample", q(pi), "policy std", log_std.exp().mean(0).tolist())
m = th.tanh(mean).clone()
m[:, -2:] = a[:, -2:]
print("Q policy mean with data gripper", q(m))
