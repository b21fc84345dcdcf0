"""Gradient steps/s of our CQL at the thesis's configuration, next to d3rlpy's CQL, SB3's SAC and the GEMM roofline.

    python benchmarks/cql_speed.py [--d3rlpy-python /path/to/venv/bin/python] [--steps 30] [--rounds 3]
                                   [--batch-size 352] [--n-actions 10]

Configuration: batch 352 (``--batch-size``), 3 x 256 networks, 10 sampled actions (``--n-actions``), Panda-sized
data (29-D observations, 9-D actions), torch on ``--threads`` threads (2 by default). Each round measures, one after
the other: our CQL, d3rlpy's CQL (in the interpreter given by ``--d3rlpy-python``, since d3rlpy pins gymnasium
1.0.0: make it with ``python -m venv V && V/bin/pip install torch==2.13.0 d3rlpy``), SB3's SAC. Medians
are reported, and for the ratios the median of the rounds' ratios (each measured back to back).

The roofline: a CQL step pushes ``batch * (1 + 3 * n_actions)`` rows forward and backward through each of the two
critics (~18.5 GFLOP at this configuration); divided into the GFLOP/s of an fp32 GEMM of the same shape it
bounds the steps/s.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import time

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import Logger

from sb3_cql import CQL
from sb3_cql.common import allocator

OBS_DIM, ACTION_DIM, BATCH, HIDDEN, N_ACTIONS, N_DATA = 29, 9, 352, [256, 256, 256], 10, 20_000

#: The start of a d3rlpy benchmark script: torch's threads, the random data as a d3rlpy dataset, the networks' encoder.
D3RLPY_DATA = """
import sys, time, numpy as np, torch, d3rlpy
torch.set_num_threads({threads})
rng = np.random.default_rng(0)
terminals = np.zeros({n}); terminals[::200] = 1
dataset = d3rlpy.dataset.MDPDataset(rng.standard_normal(({n}, {obs})).astype(np.float32),
    rng.uniform(-1, 1, ({n}, {act})).astype(np.float32), rng.standard_normal({n}).astype(np.float32), terminals)
encoder = d3rlpy.models.VectorEncoderFactory({hidden})
"""

D3RLPY_SCRIPT = (
    D3RLPY_DATA
    + """
cql = d3rlpy.algos.CQLConfig(batch_size={batch}, n_action_samples={n_actions}, actor_encoder_factory=encoder,
    critic_encoder_factory=encoder).create(device="cpu:0")
kwargs = dict(show_progress=False, logger_adapter=d3rlpy.logging.NoopAdapterFactory(), save_interval=10**9)
cql.fit(dataset, n_steps=5, n_steps_per_epoch=5, **kwargs)
start = time.perf_counter()
cql.fit(dataset, n_steps={steps}, n_steps_per_epoch={steps}, **kwargs)
print({steps} / (time.perf_counter() - start))
"""
)


def random_buffer() -> tuple[ReplayBuffer, spaces.Box, spaces.Box]:
    observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
    buffer = ReplayBuffer(N_DATA, observation_space, action_space)
    rng = np.random.default_rng(0)
    buffer.observations[:] = rng.standard_normal(buffer.observations.shape)
    buffer.next_observations[:] = rng.standard_normal(buffer.next_observations.shape)
    buffer.actions[:] = rng.uniform(-1, 1, buffer.actions.shape)
    buffer.rewards[:] = rng.standard_normal(buffer.rewards.shape)
    buffer.full = True
    return buffer, observation_space, action_space


def make_env(observation_space: spaces.Box, action_space: spaces.Box):
    import gymnasium as gym

    class SpacesEnv(gym.Env):
        """The spaces of the benchmark's data: SB3 needs an env."""

        def __init__(self):
            self.observation_space, self.action_space = observation_space, action_space

        def reset(self, *, seed=None, options=None):
            return np.zeros(OBS_DIM, np.float32), {}

        def step(self, action):
            return np.zeros(OBS_DIM, np.float32), 0.0, False, False, {}

    return SpacesEnv()


def setup(threads: int):
    """Torch's threads, and the benchmark's env and data: ``(env, buffer)``."""
    th.set_num_threads(threads)
    th.set_flush_denormal(True)
    buffer, observation_space, action_space = random_buffer()
    return make_env(observation_space, action_space), buffer


def make_cql(env, buffer: ReplayBuffer) -> CQL:
    """Our CQL at the benchmark's configuration."""
    return CQL("MlpPolicy", env, dataset=buffer, batch_size=BATCH, cql_n_actions=N_ACTIONS, policy_kwargs={"net_arch": HIDDEN})


def ours_steps_per_s(env, buffer: ReplayBuffer, steps: int) -> float:
    model = make_cql(env, buffer)
    model.learn(5)
    start = time.perf_counter()
    model.learn(steps)
    return steps / (time.perf_counter() - start)


def sac_steps_per_s(env, buffer: ReplayBuffer, steps: int) -> float:
    model = SAC("MlpPolicy", env, batch_size=BATCH, buffer_size=1, policy_kwargs={"net_arch": HIDDEN})
    model.replay_buffer = buffer
    model.set_logger(Logger(None, []))
    model.train(gradient_steps=5, batch_size=BATCH)
    start = time.perf_counter()
    model.train(gradient_steps=steps, batch_size=BATCH)
    return steps / (time.perf_counter() - start)


def d3rlpy_steps_per_s(python: str, steps: int, threads: int, retain_freed_memory: bool = False) -> float:
    script = D3RLPY_SCRIPT.format(threads=threads, n=N_DATA, obs=OBS_DIM, act=ACTION_DIM, hidden=HIDDEN, batch=BATCH,
                                  n_actions=N_ACTIONS, steps=steps)  # fmt: skip
    env = dict(os.environ)
    if retain_freed_memory:  # the allocator settings our CQL makes, given to d3rlpy through glibc's variables
        env.update(MALLOC_MMAP_THRESHOLD_=str(allocator.MMAP_THRESHOLD), MALLOC_TRIM_THRESHOLD_=str(allocator.TRIM_THRESHOLD))
    result = subprocess.run([python, "-c", script], capture_output=True, text=True, check=True, env=env)
    return float(result.stdout.strip().splitlines()[-1])


def gemm_gflops(rows: int, repeats: int = 20, rounds: int = 5) -> float:
    """The best of ``rounds`` timings of ``repeats`` fp32 products (rows x 256) @ (256 x 256): the machine's GEMM peak."""
    a, b = th.randn(rows, HIDDEN[0]), th.randn(HIDDEN[0], HIDDEN[0])
    a @ b
    best = math.inf
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(repeats):
            a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * rows * HIDDEN[0] * HIDDEN[0] * repeats / best / 1e9


def cql_step_gflop() -> float:
    rows = BATCH * (1 + 3 * N_ACTIONS)
    widths = [OBS_DIM + ACTION_DIM, *HIDDEN, 1]
    forward = 2 * rows * sum(a * b for a, b in zip(widths[:-1], widths[1:], strict=True))
    return 2 * 3 * forward / 1e9  # two critics, backward twice the forward


def main() -> None:
    global BATCH, N_ACTIONS
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--d3rlpy-python", default=None, help="interpreter with d3rlpy installed")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=BATCH, help=f"default {BATCH}, the thesis's")
    parser.add_argument("--n-actions", type=int, default=N_ACTIONS, help=f"sampled actions (default {N_ACTIONS})")
    args = parser.parse_args()
    BATCH, N_ACTIONS = args.batch_size, args.n_actions
    env, buffer = setup(args.threads)
    results: dict[str, list[float]] = {"ours": [], "d3rlpy": [], "d3rlpy_retain": [], "sac": []}
    for _ in range(args.rounds):
        results["ours"].append(ours_steps_per_s(env, buffer, args.steps))
        if args.d3rlpy_python:
            results["d3rlpy"].append(d3rlpy_steps_per_s(args.d3rlpy_python, args.steps, args.threads))
            results["d3rlpy_retain"].append(d3rlpy_steps_per_s(args.d3rlpy_python, args.steps, args.threads, True))
        results["sac"].append(sac_steps_per_s(env, buffer, args.steps))
    gflops = gemm_gflops(BATCH * (1 + 3 * N_ACTIONS))
    roofline = gflops / cql_step_gflop()
    print(f"# batch {BATCH}, net {HIDDEN}, {N_ACTIONS} sampled actions, {args.threads} threads, medians of {args.rounds}")
    ours = statistics.median(results["ours"])
    print(f"our CQL:     {ours:6.2f} gradient steps/s ({ours / roofline:.0%} of the roofline)")
    if results["d3rlpy"]:
        for key, name in (("d3rlpy", "d3rlpy CQL"), ("d3rlpy_retain", "d3rlpy CQL with our allocator settings")):
            theirs = statistics.median(results[key])
            # The machine's speed drifts between rounds: the ratio within each round (measured back to back) is
            # steadier than the ratio of the medians.
            ratio = statistics.median(o / t for o, t in zip(results["ours"], results[key], strict=True))
            print(f"{name}: {theirs:6.2f} gradient steps/s; ours / theirs: {ratio:.2f} (median of the rounds' ratios)")
    print(f"SB3 SAC:     {statistics.median(results['sac']):6.2f} gradient steps/s")
    print(f"roofline:    {roofline:6.2f} steps/s ({cql_step_gflop():.1f} GFLOP a step at {gflops:.0f} GFLOP/s fp32 GEMM)")
    print("all rounds:", {key: [round(v, 2) for v in values] for key, values in results.items()}, file=sys.stderr)


if __name__ == "__main__":
    main()
