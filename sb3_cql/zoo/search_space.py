"""CQL's and IQL's Optuna search spaces for ``python -m rl_zoo3.train --algo cql -optimize`` (``--algo calql``, ``--algo
iql``: the zoo's sampler protocol)."""

from __future__ import annotations

from typing import Any

import optuna

#: Network sizes by name, as in the zoo's off-policy samplers.
NET_ARCHS = {"medium": [256, 256], "large": [256, 256, 256], "verybig": [512, 512, 512]}
#: Lengths of the behaviour-cloning warm start, in gradient steps (0: none); one as long as the budget (``-n``, which
#: the zoo's samplers do not see) makes the trial a pure imitation run.
BC_STEPS = [0, 5000, 10000, 20000]
#: Weights of the imitation anchor on the actor after the warm start (0: none, CQL as defined; 0.4: TD3+BC's alpha 2.5).
ACTOR_BC_WEIGHTS = [0.0, 0.4, 1.0, 4.0]
#: SB3's n-step returns (``n_steps``): steps summed before the TD target bootstraps (1: one-step backups).
N_STEPS = [1, 3, 5, 10]
#: The critics' rewards by name, as ``(reward_scale, reward_bias)``: the data's 0/1, or the thesis code's 4r - 2.
REWARDS = {"data": (1.0, 0.0), "shifted": (4.0, -2.0)}


def sample_cql_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Sample the conservative weight, both learning rates, batch size, sampled actions, network size, the warm start
    (its length, and its learning rate), the actor's anchor, the rewards and n-step returns (Cal-QL's too)."""
    params = {
        "cql_alpha": trial.suggest_float("cql_alpha", 0.1, 20.0, log=True),
        "learning_rate": trial.suggest_float("learning_rate", 3e-5, 1e-3, log=True),
        "actor_learning_rate": trial.suggest_float("actor_learning_rate", 1e-5, 1e-3, log=True),
        "batch_size": trial.suggest_categorical("batch_size", [128, 256, 352, 512]),
        "cql_n_actions": trial.suggest_categorical("cql_n_actions", [4, 10, 20]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        "bc_steps": trial.suggest_categorical("bc_steps", BC_STEPS),
        "actor_bc_weight": trial.suggest_categorical("actor_bc_weight", ACTOR_BC_WEIGHTS),
        "reward": trial.suggest_categorical("reward", list(REWARDS)),
        "n_steps": trial.suggest_categorical("n_steps", N_STEPS),
    }
    if params["bc_steps"] > 0:  # (without a warm start the rate is unused)
        params["bc_learning_rate"] = trial.suggest_float("bc_learning_rate", 1e-4, 3e-3, log=True)
    return convert_params(params)


def convert_params(params: dict[str, Any]) -> dict[str, Any]:
    """A trial's raw parameters as CQL's or IQL's keywords (``net_arch`` name -> ``policy_kwargs``, ``reward`` name ->
    ``reward_scale`` and ``reward_bias``)."""
    hyperparams = dict(params)
    hyperparams["policy_kwargs"] = {"net_arch": NET_ARCHS[hyperparams.pop("net_arch")]}
    if "reward" in hyperparams:  # (studies from before it was sampled)
        hyperparams["reward_scale"], hyperparams["reward_bias"] = REWARDS[hyperparams.pop("reward")]
    return hyperparams


def sample_iql_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Sample IQL's expectile, temperature, discount, learning rate, batch size, network size, rewards, n-step returns,
    best-of-N acting, the twins' combination and the actor's extraction (and the anchor's weight where it has one)."""
    params = {
        "expectile": trial.suggest_categorical("expectile", [0.5, 0.7, 0.8, 0.9, 0.95]),
        "temperature": trial.suggest_float("temperature", 0.5, 30.0, log=True),
        "gamma": trial.suggest_categorical("gamma", [0.99, 0.995, 0.999]),
        "learning_rate": trial.suggest_float("learning_rate", 3e-5, 1e-3, log=True),
        "batch_size": trial.suggest_categorical("batch_size", [128, 256, 512]),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        "reward": trial.suggest_categorical("reward", list(REWARDS)),
        "n_steps": trial.suggest_categorical("n_steps", N_STEPS),
        "best_of_n": trial.suggest_categorical("best_of_n", [1, 8, 32]),
        "q_agg": trial.suggest_categorical("q_agg", ["min", "mean"]),
        "actor_loss_type": trial.suggest_categorical("actor_loss_type", ["awr", "ddpg_awr"]),
    }
    if params["actor_loss_type"] != "awr":
        params["actor_bc_weight"] = trial.suggest_float("actor_bc_weight", 0.4, 10.0, log=True)
    return convert_params(params)
