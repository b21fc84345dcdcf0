"""Gradient steps/s of our IQL at the shipped configuration next to d3rlpy's IQL, and best-of-N's cost per action.

    python benchmarks/iql_speed.py [--d3rlpy-python /path/to/venv/bin/python] [--steps 200] [--rounds 3]
                                   [--batch-size 256] [--best-of-n 32]

Configuration: ``hyperparams/iql.yml``'s (batch 256, 3 x 256 networks, expectile 0.9, temperature 10, gamma 0.999),
Panda-sized data (29-D observations, 9-D actions, as ``cql_speed.py``), torch on ``--threads`` threads (2 by
default). Each round measures, one after the other: our IQL, d3rlpy's IQL at the same batch and networks (in the
interpreter given by ``--d3rlpy-python``, since d3rlpy pins gymnasium 1.0.0: make it with
``python -m venv V && V/bin/pip install torch==2.13.0 d3rlpy``), and the time of ``predict`` on one observation with
the actor's action and with best-of-N. Medians are reported, and for the ratio the median of the rounds' ratios
(each measured back to back).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import numpy as np
from cql_speed import ACTION_DIM, D3RLPY_DATA, HIDDEN, N_DATA, OBS_DIM, setup

from sb3_cql import IQL

BATCH = 256

D3RLPY_SCRIPT = (
    D3RLPY_DATA
    + """
iql = d3rlpy.algos.IQLConfig(batch_size={batch}, gamma=0.999, expectile=0.9, weight_temp=10.0,
    actor_encoder_factory=encoder, critic_encoder_factory=encoder, value_encoder_factory=encoder).create(device="cpu:0")
kwargs = dict(show_progress=False, logger_adapter=d3rlpy.logging.NoopAdapterFactory(), save_interval=10**9)
iql.fit(dataset, n_steps=5, n_steps_per_epoch=5, **kwargs)
start = time.perf_counter()
iql.fit(dataset, n_steps={steps}, n_steps_per_epoch={steps}, **kwargs)
print({steps} / (time.perf_counter() - start))
"""
)


def make_iql(env, buffer, best_of_n: int = 1) -> IQL:
    """Our IQL at the shipped configuration."""
    return IQL("MlpPolicy", env, dataset=buffer, batch_size=BATCH, gamma=0.999, expectile=0.9, temperature=10.0,
               best_of_n=best_of_n, policy_kwargs={"net_arch": HIDDEN})  # fmt: skip


def ours_steps_per_s(env, buffer, steps: int) -> float:
    model = make_iql(env, buffer)
    model.learn(5)
    start = time.perf_counter()
    model.learn(steps)
    return steps / (time.perf_counter() - start)


def d3rlpy_steps_per_s(python: str, steps: int, threads: int) -> float:
    script = D3RLPY_SCRIPT.format(threads=threads, n=N_DATA, obs=OBS_DIM, act=ACTION_DIM, hidden=HIDDEN, batch=BATCH,
                                  steps=steps)  # fmt: skip
    result = subprocess.run([python, "-c", script], capture_output=True, text=True, check=True)
    return float(result.stdout.strip().splitlines()[-1])


def predict_ms(model: IQL, calls: int = 200) -> float:
    """Milliseconds of one deterministic ``predict`` on one observation (a new observation each call)."""
    observations = np.random.default_rng(0).standard_normal((calls, OBS_DIM)).astype(np.float32)
    model.predict(observations[0], deterministic=True)
    start = time.perf_counter()
    for observation in observations:
        model.predict(observation, deterministic=True)
    return 1000 * (time.perf_counter() - start) / calls


def main() -> None:
    global BATCH
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--d3rlpy-python", default=None, help="interpreter with d3rlpy installed")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=BATCH, help=f"default {BATCH}, hyperparams/iql.yml's")
    parser.add_argument("--best-of-n", type=int, default=32, help="candidates of best-of-N (default 32)")
    args = parser.parse_args()
    BATCH = args.batch_size
    env, buffer = setup(args.threads)
    results: dict[str, list[float]] = {"ours": [], "d3rlpy": [], "predict_1": [], "predict_n": []}
    for _ in range(args.rounds):
        results["ours"].append(ours_steps_per_s(env, buffer, args.steps))
        if args.d3rlpy_python:
            results["d3rlpy"].append(d3rlpy_steps_per_s(args.d3rlpy_python, args.steps, args.threads))
        model = make_iql(env, buffer)
        results["predict_1"].append(predict_ms(model))
        model.policy.best_of_n = args.best_of_n
        results["predict_n"].append(predict_ms(model))
    print(f"# batch {BATCH}, net {HIDDEN}, {args.threads} threads, medians of {args.rounds}")
    ours = statistics.median(results["ours"])
    print(f"our IQL:     {ours:7.2f} gradient steps/s")
    if results["d3rlpy"]:
        theirs = statistics.median(results["d3rlpy"])
        ratio = statistics.median(o / t for o, t in zip(results["ours"], results["d3rlpy"], strict=True))
        print(f"d3rlpy IQL:  {theirs:7.2f} gradient steps/s; ours / theirs: {ratio:.2f} (median of the rounds' ratios)")
    one, many = statistics.median(results["predict_1"]), statistics.median(results["predict_n"])
    print(f"predict, one observation: {one:.2f} ms with the actor's action, {many:.2f} ms with best-of-{args.best_of_n} "
          f"({many / one:.1f}x)")  # fmt: skip
    print("all rounds:", {key: [round(v, 2) for v in values] for key, values in results.items()}, file=sys.stderr)


if __name__ == "__main__":
    main()
