"""CQL with its actor started from a trained BC model: success (10 episodes, env seed 1000) every K gradient steps.

Usage: python results/diagnostics/cql_from_clone.py BC_MODEL.zip STEPS K '{"batch_size": 128, "bc_steps": 3000, ...}' [DATASET]
(keywords: CQL's, plus "clip_backup" or "mean_backup": true for the classes below; DATASET: the Minari id CQL trains on,
sb3cql/Panda-v0/noisy-delta-v0 by default, session 4's data)
(results/dataset_comparison.md, session 4 tables "Starting from a working clone" and after). The final model is saved
in the CSV log's folder (cql_from_clone_logs/TIME-PID/model.zip) for sb3_cql.evaluate. Throwaway-grade.
"""

import json
import os
import sys
import time

import gymnasium as gym
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.sac.policies import LOG_STD_MIN

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import BC, CQL
from sb3_cql.evaluate import success_rate

th.set_num_threads(1)
bc_path, steps, every, kwargs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), json.loads(sys.argv[4])
clip_backup = kwargs.pop("clip_backup", False)
mean_backup = kwargs.pop("mean_backup", False)


class ClippedCQL(CQL):
    """With ``"clip_backup": true`` in the keywords (session 9's test): the backup's next-state values clamped to the
    returns the rewards allow, min_r / (1 - gamma) to max_r / (1 - gamma) (rewards 0/1 after reward_scale and bias)."""

    def _next_q_values(self, *args, **kwargs):
        values = super()._next_q_values(*args, **kwargs)
        rewards = sorted((self.reward_bias, self.reward_scale + self.reward_bias))
        return values.clamp(rewards[0] / (1 - self.gamma), rewards[1] / (1 - self.gamma))


class MeanBackupCQL(CQL):
    """With ``"mean_backup": true`` (session 9's test): the backup scores the policy's mean action at s' (TD3's
    target), not a sample: Q of the deterministic policy that is evaluated, not of its noisy samples."""

    def _next_q_values(self, next_observations, next_policy, ent_coef):
        mean_actions, log_std = next_policy
        return super()._next_q_values(next_observations, (mean_actions, th.full_like(log_std, LOG_STD_MIN)), ent_coef)


dataset = sys.argv[5] if len(sys.argv) > 5 else "sb3cql/Panda-v0/noisy-delta-v0"
env_kwargs = {"action_mode": "delta"}
env = gym.make("Panda-v0", **env_kwargs)
bc = BC.load(bc_path)
model = (MeanBackupCQL if mean_backup else ClippedCQL if clip_backup else CQL)(
    "MlpPolicy", env, dataset=dataset, policy_kwargs=dict(net_arch=[256, 256, 256]), seed=1, **kwargs
)
model.actor.load_state_dict(bc.actor.state_dict())
model.policy.actor.load_state_dict(bc.actor.state_dict())
log_dir = f"cql_from_clone_logs/{int(time.time())}-{os.getpid()}"  # two runs started together get their own
model.set_logger(configure(log_dir, ["csv"]))


def ev():
    return success_rate(model, "Panda-v0", n_episodes=10, seed=1000, env_kwargs=env_kwargs)


def spread():
    """The policy's mean pre-tanh standard deviation per action dimension over 512 sampled states (the Q diagnostics
    are in the CSV log: the logger's values are cleared when it writes)."""
    data = model.replay_buffer.sample(512)
    with th.no_grad():
        _, log_std, _ = model.actor.get_action_dist_params(data.observations)
    return log_std.exp().mean(0).numpy().round(2).tolist()


print(0, ev(), flush=True)
done = 0
while done < steps:
    model.learn(every, reset_num_timesteps=False, log_interval=every)
    done += every
    print(done, ev(), "std", spread(), flush=True)
model.save(log_dir + "/model.zip")
print("saved", log_dir + "/model.zip", flush=True)
