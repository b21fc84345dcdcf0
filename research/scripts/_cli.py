"""What the experiment scripts' command lines share: argument types, and the CQL model started from a BC clone.

The scripts import it as ``_cli`` (``python research/scripts/<name>.py`` puts this folder first on ``sys.path``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import gymnasium as gym

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import BC, CQL

#: The keywords a script's JSON argument may give: CQL's, less those the scripts set themselves.
CQL_KEYWORDS = CQL.known_keywords() - {"policy", "env", "dataset", "seed", "_init_setup_model"}


def positive_int(text: str) -> int:
    """An ``argparse`` type: an integer of at least 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def cql_keywords(text: str, extra_keys: tuple[str, ...] = ()) -> dict[str, Any]:
    """An ``argparse`` type: a JSON object of CQL's keywords (and of ``extra_keys``, a script's own). The studies'
    CQL has a fixed weight, as when they were run (the package's default learns it since 2026-12-06): without
    ``cql_target_action_gap`` in the object, it is ``None``."""
    try:
        kwargs = json.loads(text)
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(f"not JSON ({error}): {text}") from error
    if not isinstance(kwargs, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object, got {text}")
    unknown = sorted(set(kwargs) - set(extra_keys) - CQL_KEYWORDS)
    if unknown:
        raise argparse.ArgumentTypeError(f"not CQL keywords: {', '.join(unknown)}")
    return {"cql_target_action_gap": None, **kwargs}


def cql_from_clone(
    bc_model: str, dataset_id: str, kwargs: dict[str, Any], algorithm: type[CQL] = CQL, env_id: str = "Panda-v0"
) -> CQL:
    """A CQL model (``algorithm``: CQL or a variant of it) on ``dataset_id`` in ``env_id``'s delta actions, seed 1,
    whose actor is the saved BC clone's (its network sizes unless ``kwargs`` give ``policy_kwargs``)."""
    clone = BC.load(bc_model)
    kwargs = {**kwargs, "policy_kwargs": {"net_arch": clone.policy_kwargs["net_arch"], **kwargs.get("policy_kwargs", {})}}
    model = algorithm("MlpPolicy", gym.make(env_id, action_mode="delta"), dataset=dataset_id, seed=1, **kwargs)
    model.actor.load_state_dict(clone.actor.state_dict())
    return model


def train(model: BC | CQL, steps: int) -> int:
    """Make ``steps`` more gradient steps, then write one row of the model's CSV log; return ``steps``."""
    model.learn(steps, reset_num_timesteps=False, log_interval=0)
    model.logger.dump(step=model.num_timesteps)
    return steps
