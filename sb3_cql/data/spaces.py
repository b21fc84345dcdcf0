"""Does this model, or this dataset, fit this env (:func:`check_spaces`), and the action mode a model was trained in
(:func:`env_kwargs_for`). The tasks load only when a task's spaces are made, and Minari is never loaded here.
"""

from __future__ import annotations

import inspect
import sys
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_cql.data.errors import DatasetError


def describe_space(space: gym.Space) -> str:
    """``space``'s repr on one line (numpy wraps long bounds)."""
    return " ".join(repr(space).split())


def dataset_name(dataset: Any) -> str:
    """A Minari dataset's id, or its folder for a dataset without one: the name every error gives."""
    return dataset.spec.dataset_id if dataset.spec else str(dataset.storage.data_path)


def env_name(env: gym.Env, env_id: str) -> str:
    """``env_id``, with the env's action mode where it has one: ``Panda-v0 (action_mode 'absolute')``."""
    action_mode = getattr(env.unwrapped, "action_mode", None)
    return f"{env_id} (action_mode {action_mode!r})" if action_mode else env_id


def space_mismatch(space: gym.Space, env_space: gym.Space, what: str = "observation") -> str | None:
    """Why ``space`` (``what``: ``"action"``, ``"observation"``) is not ``env_space``, in a few words (``""`` where the
    spaces say it), or ``None`` where it is: Box spaces fit with the same shape and close bounds, whatever their dtypes."""
    if isinstance(space, spaces.Box) and isinstance(env_space, spaces.Box):
        if space.shape != env_space.shape:
            return f"its shape {space.shape}, not {env_space.shape}: made for another task?"
        if not (np.allclose(space.low, env_space.low) and np.allclose(space.high, env_space.high)):
            return f"other {what} bounds: made for another action mode or task?"
        return None
    return None if space == env_space else ""


def check_spaces(
    source: Any, observation_space: gym.Space | None, action_space: gym.Space | None, env: str = "the env"
) -> None:
    """Refuse a model or a dataset whose observation or action space is not the env's (:func:`space_mismatch`; Dict
    observations key by key): a :class:`DatasetError` for a dataset, a ``ValueError`` for a model. A source without a
    space (a PD controller) fits every env.

    :param source: a Minari dataset, an SB3 model, or anything with ``observation_space`` and ``action_space``.
    :param observation_space: the env's observation space; ``None``: not checked.
    :param action_space: the env's action space; ``None``: not checked.
    :param env: the env, in the message (:func:`env_name`).
    """
    minari = sys.modules.get("minari")  # a dataset is made by Minari: without it loaded, the source is no dataset
    is_dataset = minari is not None and isinstance(source, minari.MinariDataset)
    error, subject = (DatasetError, f"dataset {dataset_name(source)}: its") if is_dataset else (ValueError, "the model's")
    pairs = [("observation", getattr(source, "observation_space", None), observation_space),
             ("action", getattr(source, "action_space", None), action_space)]  # fmt: skip
    data_observations = pairs[0][1]
    if isinstance(data_observations, spaces.Dict) and isinstance(observation_space, spaces.Dict):
        if set(data_observations.spaces) != set(observation_space.spaces):
            raise error(
                f"{subject} observation keys {sorted(data_observations.spaces)} are not those of {env}: "
                f"{sorted(observation_space.spaces)}"
            )
        pairs[:1] = [(f"observation {key!r}", data_observations[key], observation_space[key])
                     for key in observation_space.spaces]  # fmt: skip
    for what, space, env_space in pairs:
        if space is None or env_space is None:
            continue
        reason = space_mismatch(space, env_space, what.split()[0])
        if reason is not None:
            raise error(
                f"{subject} {what} space {describe_space(space)} is not that of {env}: {describe_space(env_space)}"
                + (f" ({reason})" if reason else "")
            )


def default_action_mode() -> str:
    """The action mode of a task made without ``action_mode``."""
    import envs  # the tasks and their simulator: see the module's docstring

    return inspect.signature(envs.PandaGraspEnv).parameters["action_mode"].default


def env_spaces(env_id: str, env_kwargs: dict[str, Any] | None = None) -> tuple[gym.Space, gym.Space]:
    """The observation and action spaces of ``env_id`` made with ``env_kwargs`` (the env is made and closed)."""
    import envs  # noqa: F401  (registers the tasks: see the module's docstring)

    env = gym.make(env_id, **(env_kwargs or {}))
    try:
        return env.observation_space, env.action_space
    finally:
        env.close()


def env_kwargs_for(policy: Any, env_id: str, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """``env_kwargs`` of ``env_id`` with the ``action_mode`` whose action space is ``policy``'s (an SB3 model; a
    policy without ``action_space``, a PD controller, gets them unchanged). ``ValueError`` when the observation space
    is not the task's, or the ``action_mode`` given or none is the policy's."""
    from envs.robot import ACTION_MODES  # the tasks and their simulator: see the module's docstring

    env_kwargs = dict(env_kwargs or {})
    action_space = getattr(policy, "action_space", None)
    if action_space is None:
        return env_kwargs
    given = env_kwargs.get("action_mode")
    if given is not None and given not in ACTION_MODES:
        raise ValueError(f"action_mode {given!r} is none of {env_id}'s: {', '.join(ACTION_MODES)}")
    spaces_by_mode = {mode: env_spaces(env_id, {**env_kwargs, "action_mode": mode}) for mode in ACTION_MODES}
    check_spaces(policy, spaces_by_mode[given or default_action_mode()][0], None, env_id)
    matching = [mode for mode, (_, space) in spaces_by_mode.items() if space_mismatch(action_space, space) is None]
    if not matching:
        modes = "; ".join(f"action_mode {mode!r}: {describe_space(space)}" for mode, (_, space) in spaces_by_mode.items())
        raise ValueError(
            f"the model's action space {describe_space(action_space)} is that of no action mode of {env_id} ({modes})"
        )
    if given is not None and given not in matching:
        raise ValueError(
            f"the model's action space {describe_space(action_space)} is that of action_mode {matching[0]!r}, not that "
            f"of the action_mode {given!r} asked for: {describe_space(spaces_by_mode[given][1])}"
        )
    return {**env_kwargs, "action_mode": given or matching[0]}
