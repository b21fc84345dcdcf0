"""Success rate of a policy on each of the tasks: a model trained on one task, evaluated on all three.

    python -m sb3_cql.evaluate logs/cql/Panda-v0_1/best_model.zip --algo cql -n 100 --seed 0
    python -m sb3_cql.evaluate pid --env Panda-v0 PandaForce-v0 -n 100
    python -m sb3_cql.evaluate pid-regrasp --env PandaForce-v0 -n 100      # the PD controller that regrasps
    python -m sb3_cql.evaluate logs/bc/Panda-v0_1/best_model.zip --algo bc --env-kwargs action_mode:"'delta'"

``MODEL`` is a saved SB3 model (``--algo`` is its RL-Zoo3 name: cql, sac, ...), ``pid`` for the PD controller or
``pid-regrasp`` for the PD controller that reopens and grasps again when it has lost the object.
Episodes are deterministic given ``--seed``: the env is reset with it once, and its own generator seeds the rest.
"""

from __future__ import annotations

import argparse
from typing import Any

import gymnasium as gym
import numpy as np
from rl_zoo3.utils import StoreDict
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv

import envs


def success_rate(
    policy: Any,
    env_id: str,
    n_episodes: int = 100,
    seed: int = 0,
    deterministic: bool = True,
    env_kwargs: dict[str, Any] | None = None,
) -> float:
    """Fraction of ``n_episodes`` episodes of ``env_id`` that ``policy`` (anything with SB3's ``predict``) succeeds in.

    :param policy: an SB3 model or :class:`envs.PDController`.
    :param env_id: the task.
    :param n_episodes: episodes.
    :param seed: seed of the env's first reset.
    :param deterministic: use the policy's deterministic actions.
    :param env_kwargs: keywords of the env (``action_mode``: the one the policy was trained in).
    """
    env = DummyVecEnv([lambda: Monitor(gym.make(env_id, **(env_kwargs or {})))])
    env.seed(seed)
    successes: list[bool] = []

    def record_success(local_vars: dict[str, Any], _globals: dict[str, Any]) -> None:
        if local_vars["done"]:
            successes.append(bool(local_vars["info"].get("is_success", False)))

    evaluate_policy(policy, env, n_eval_episodes=n_episodes, deterministic=deterministic, callback=record_success)
    env.close()
    return float(np.mean(successes))


def load_policy(model: str, algo: str | None, env_id: str, env_kwargs: dict[str, Any] | None = None) -> Any:
    """The PD controller for ``pid`` or ``pid-regrasp`` (for ``env_id`` made with ``env_kwargs``), else the SB3
    model saved at ``model`` (``algo``: a key of RL-Zoo3's ALGOS)."""
    if model in envs.CONTROLLERS:
        env = gym.make(env_id, **(env_kwargs or {}))
        controller = envs.PDController.for_env(env, **envs.CONTROLLERS[model])
        env.close()
        return controller
    if algo is None:
        raise ValueError("a saved model needs --algo (cql, sac, ...)")
    from rl_zoo3.utils import ALGOS  # our plugin adds cql

    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}: one of {sorted(ALGOS)}")
    # As the zoo's enjoy does: an off-policy model needs no replay buffer to act.
    kwargs = {"buffer_size": 1} if issubclass(ALGOS[algo], OffPolicyAlgorithm) else {}
    return ALGOS[algo].load(model, device="cpu", **kwargs)


class EnvKwargs(StoreDict):
    """RL-Zoo3's ``KEY:VALUE`` dict action, with a usage error (not a traceback from ``eval``) for an item that is
    not one: typically the model's path, swallowed when it comes after ``--env-kwargs``."""

    def __call__(self, parser, namespace, values, option_string=None):
        for item in values:
            key, _, value = item.partition(":")
            try:
                eval(value)  # as StoreDict does next
                valid = bool(key)
            except Exception:  # SyntaxError for the empty value of an item without ":", NameError, ...
                valid = False
            if not valid:
                parser.error(
                    f"{option_string} takes KEY:VALUE items with a Python value (e.g. action_mode:\"'delta'\"), got "
                    f"{item!r} (a string needs quotes; the model goes before {option_string})"
                )
        super().__call__(parser, namespace, values, option_string)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_cql.evaluate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("model", help="path of a saved SB3 model, or pid, or pid-regrasp")
    parser.add_argument("--algo", default=None, help="RL-Zoo3 name of the model's algorithm (cql, sac, ...)")
    parser.add_argument("--env", nargs="+", default=list(envs.ENV_IDS), choices=list(envs.ENV_IDS))
    parser.add_argument("-n", "--n-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of the deterministic ones")
    parser.add_argument("--env-kwargs", type=str, nargs="+", action=EnvKwargs, default={},
                        help="env keywords as the zoo's, e.g. action_mode:\"'delta'\" (the model's action mode)")  # fmt: skip
    args = parser.parse_args(argv)
    model = None if args.model in envs.CONTROLLERS else load_policy(args.model, args.algo, args.env[0])  # loaded once
    for env_id in args.env:
        policy = (
            model if model is not None else load_policy(args.model, args.algo, env_id, args.env_kwargs)
        )  # PD: one per task
        rate = success_rate(policy, env_id, args.n_episodes, args.seed, not args.stochastic, args.env_kwargs)
        print(f"{env_id}: success rate {rate:.3f} over {args.n_episodes} episodes (seed {args.seed})")


if __name__ == "__main__":
    main()
