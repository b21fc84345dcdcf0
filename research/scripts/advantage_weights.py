"""How an IQL model's advantage weights spread over a dataset's own transitions: how many samples the actor learns from.

Usage: python research/scripts/advantage_weights.py MODEL.zip [--dataset ID] [--episodes N] [--weights T:M ...]
[--threads N]

At every step of the dataset's first ``--episodes`` episodes, the advantage IQL's actor is weighted by,
``A = Q'(s, a) - V(s)`` (the target critics' value of the data's action combined by the model's ``q_agg``, minus
its value network, as :meth:`sb3_cql.IQL.train` computes it), and the weights ``min(exp(T * A), M)``, at the
model's own ``temperature`` and ``max_weight`` and at each ``T:M`` of ``--weights``. For each it prints the mean
weight, the share of samples at the clip ``M``, and the effective sample size as a share of the samples,
``(sum w)^2 / (N * sum w^2)``: 1 when every sample counts alike (a clone), 0.05 when the regression learns from as
many samples as one twentieth of the data. Also printed: the advantages' quantiles, and the critics' values against
the floor of the data's discounted returns in the critics' units (``min(reward_bias, 0) / (1 - gamma)``, for raw
rewards of at least 0, as the tasks' are): how often, and how far, they sink below any return the data can have.

Printed::

    MODEL on DATASET, 200 episodes, 138516 steps
    advantage quantiles 0.01 / 0.5 / 0.99 / 0.999 / max: -0.12 / -0.00 / +0.10 / +4.29 / +10.1
    Q'(s, a) below the returns' floor 0: 0.98 of the steps, 0.01 below -1, the least -82.3
    T 50 M 100 (the model's): mean weight 2.69, at the clip 0.011, effective sample size 0.056 of the samples
    T 50 M 10: mean weight 1.42, at the clip 0.029, effective sample size 0.363 of the samples

Nothing is written; torch runs ``--threads`` threads (1 by default).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch as th
from _cli import positive_int

import sb3_cql  # noqa: F401  (registers cql, bc and iql with the zoo)
from sb3_cql import IQL
from sb3_cql.data import DatasetError, load_dataset

BATCH = 20_000


def weight_setting(text: str) -> tuple[float, float]:
    """An ``argparse`` type: ``T:M``, a temperature of at least 0 and a positive largest weight."""
    try:
        temperature, max_weight = (float(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be TEMPERATURE:MAX_WEIGHT, such as 50:10, got {text!r}") from None
    if not (np.isfinite(temperature) and temperature >= 0 and np.isfinite(max_weight) and max_weight > 0):
        raise argparse.ArgumentTypeError(f"needs a temperature >= 0 and a max weight > 0, got {text!r}")
    return temperature, max_weight


def advantages(model: IQL, observations: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Q'(s, a), Q'(s, a) - V(s))`` at each of the data's steps, as IQL's update computes them."""
    q_values, values = [], []
    with th.no_grad():
        for start in range(0, len(observations), BATCH):
            obs = th.as_tensor(observations[start : start + BATCH], dtype=th.float32, device=model.device)
            act = th.as_tensor(actions[start : start + BATCH], dtype=th.float32, device=model.device)
            q_values.append(model.target_q_values(obs, act).flatten().cpu().numpy())
            values.append(model.state_values(obs).flatten().cpu().numpy())
    q = np.concatenate(q_values)
    return q, q - np.concatenate(values)


def weights_line(advantage: np.ndarray, temperature: float, max_weight: float, own: bool) -> str:
    """The mean weight, the share at the clip and the effective sample size of ``min(exp(T * A), M)``."""
    with np.errstate(over="ignore"):
        weights = np.minimum(np.exp(temperature * advantage), max_weight)
    ess = weights.sum() ** 2 / (len(weights) * (weights**2).sum())
    setting = f"T {temperature:g} M {max_weight:g}" + (" (the model's)" if own else "")
    return (
        f"{setting}: mean weight {weights.mean():.2f}, at the clip {np.mean(weights >= max_weight):.3f}, effective "
        f"sample size {ess:.3f} of the samples"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python research/scripts/advantage_weights.py", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    parser.add_argument("model", help="a saved IQL model (.zip)")
    parser.add_argument("--dataset", default="sb3cql/PandaForce-v0/noisy-regrasp-yaw-delta-1k-v0", help="dataset id")
    parser.add_argument("--episodes", type=positive_int, default=200, help="the dataset's first N episodes (200)")
    parser.add_argument("--weights", type=weight_setting, nargs="*", default=[], metavar="T:M",
                        help="more temperatures and max weights to read the same advantages with")  # fmt: skip
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    th.set_num_threads(args.threads)
    try:
        model = IQL.load(args.model, device="cpu")
        dataset = load_dataset(args.dataset)
    except (ValueError, OSError, DatasetError) as error:
        sys.exit(f"error: {error}")
    if getattr(model.policy, "action_chunk", 1) != 1:
        sys.exit(f"error: {args.model} acts in chunks; this reads one action a step")
    episodes = list(dataset.iterate_episodes(range(min(args.episodes, dataset.total_episodes))))
    observations = np.concatenate([episode.observations[:-1] for episode in episodes])
    actions = np.concatenate([episode.actions for episode in episodes])
    if observations.shape[1:] != model.observation_space.shape or actions.shape[1:] != model.action_space.shape:
        sys.exit(f"error: {args.dataset}'s spaces do not match {args.model}'s")
    q, advantage = advantages(model, observations, actions)

    floor = min(model.reward_bias, 0.0) / (1 - model.gamma) if model.gamma < 1 else float("nan")
    quantiles = np.quantile(advantage, [0.01, 0.5, 0.99, 0.999])
    print(f"{args.model} on {args.dataset}, {len(episodes)} episodes, {len(advantage)} steps")
    print(f"advantage quantiles 0.01 / 0.5 / 0.99 / 0.999 / max: {' / '.join(f'{v:+.2f}' for v in quantiles)} / "
          f"{advantage.max():+.1f}")  # fmt: skip
    print(f"Q'(s, a) below the returns' floor {floor:g}: {np.mean(q < floor):.2f} of the steps, "
          f"{np.mean(q < floor - 1):.2f} below {floor - 1:g}, the least {q.min():.1f}")  # fmt: skip
    print(weights_line(advantage, model.temperature, model.max_weight, own=True))
    for temperature, max_weight in args.weights:
        print(weights_line(advantage, temperature, max_weight, own=False))


if __name__ == "__main__":
    main()
