"""Does ``torch.compile`` make our CQL step faster? The step with the critics compiled by Inductor, against ours.

    python benchmarks/cql_compile.py [--steps 20] [--rounds 6] [--threads 2]

Two CQL models at the thesis's configuration (``cql_speed.py``'s data and sizes): ours as shipped (the critics through
``sb3_cql/cql/fused_mlp.py``), and one whose critics run as SB3's ``nn.Sequential`` through ``torch.compile`` (Inductor
fuses the ReLUs, their gradients and the loss's element-wise work around the matrix products). Each round trains both
for ``--steps`` gradient steps back to back; reported: the medians and the median of the rounds' ratios.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch as th
from cql_speed import BATCH, HIDDEN, N_ACTIONS, make_cql, setup

from sb3_cql import CQL


def make_model(env, buffer, compiled: bool) -> CQL:
    model = make_cql(env, buffer)
    if compiled:
        critic = th.compile(lambda observations, actions: model.critic(observations, actions))
        model.critic.forward_fused = critic  # type: ignore[method-assign]
    model.learn(5)  # compiles (Inductor's first call) outside the timings
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    env, buffer = setup(args.threads)
    models = {"ours": make_model(env, buffer, False), "compiled": make_model(env, buffer, True)}
    results: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.rounds):
        for name, model in models.items():
            start = time.perf_counter()
            model.learn(args.steps)
            results[name].append(args.steps / (time.perf_counter() - start))
    print(f"# batch {BATCH}, net {HIDDEN}, {N_ACTIONS} sampled actions, {args.threads} threads, medians of {args.rounds}")
    print(f"our CQL:                    {statistics.median(results['ours']):6.2f} gradient steps/s")
    print(f"critics via torch.compile:  {statistics.median(results['compiled']):6.2f} gradient steps/s")
    ratio = statistics.median(c / o for c, o in zip(results["compiled"], results["ours"], strict=True))
    print(f"compiled / ours: {ratio:.2f} (median of the rounds' ratios)")
    print("all rounds:", {name: [round(v, 2) for v in values] for name, values in results.items()}, file=sys.stderr)


if __name__ == "__main__":
    main()
