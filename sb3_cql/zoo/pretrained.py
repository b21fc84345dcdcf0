"""The ``-i`` model, read before SB3 loads it: its saved attributes (``action_chunk``), and whether its spaces fit the
training env, by SB3's own check, so that a misfit is one line rather than SB3's traceback."""

from __future__ import annotations

from typing import Any

from gymnasium import spaces
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.utils import check_for_correct_spaces


def saved_data(model_path: str) -> dict[str, Any]:
    """The attributes saved in the SB3 model ``model_path`` (its ``data``: spaces, ``action_chunk``, ...)."""
    data, _, _ = load_from_zip_file(model_path, device="cpu", load_data=True)
    return data or {}


def saved_spaces(model_path: str) -> tuple[Any, Any] | None:
    """The observation and action spaces saved in the SB3 model ``model_path``, if they are gymnasium spaces (SB3
    converts older ones itself when it loads the model)."""
    data = saved_data(model_path)
    saved = (data.get("observation_space"), data.get("action_space"))
    return saved if all(isinstance(space, spaces.Space) for space in saved) else None


def misfit(saved: tuple[Any, Any] | None, env: Any) -> str | None:
    """How a model with the ``saved`` spaces does not fit ``env``, by SB3's check when it loads a model with an env
    (``check_for_correct_spaces``), or None where it fits."""
    if saved is None:
        return None
    try:
        check_for_correct_spaces(env, *saved)
    except ValueError as error:
        return " ".join(str(error).split())
    return None
