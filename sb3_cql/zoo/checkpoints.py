"""A run's models and checkpoints: saves that leave a file whole or none for any algorithm the zoo trains, the online
transitions kept with a fine-tuning's checkpoints (``-i CHECKPOINT`` loads them), and a damaged model named on one
line with the last good checkpoint beside it."""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CheckpointCallback

from sb3_cql.common.atomic import saved_model_problem, with_atomic_saves
from sb3_cql.zoo.errors import fail


def atomic_saves(model: Any) -> None:
    """Make the saves of ``model`` (one of SB3's or another library's algorithms) leave a file whole or none, as ours
    do: its class becomes :func:`~sb3_cql.common.atomic.with_atomic_saves` of it, its behaviour otherwise the same."""
    if isinstance(model, BaseAlgorithm) and not getattr(type(model), "saves_atomically", False):
        model.__class__ = with_atomic_saves(type(model))


def checkpoint_parts(model_path: Path) -> tuple[str, int] | None:
    """The prefix and step of a checkpoint ``<prefix>_<N>_steps.zip`` (SB3's ``CheckpointCallback``), else None."""
    parts = model_path.stem.rsplit("_", 2)  # rl_model, <N>, steps
    if len(parts) != 3 or parts[2] != "steps" or not parts[1].isdigit():
        return None
    return parts[0], int(parts[1])


def checkpoint_buffer(model_path: Path) -> Path | None:
    """The replay buffer saved with a checkpoint ``rl_model_<N>_steps.zip`` (SB3's ``CheckpointCallback``), if any."""
    parts = checkpoint_parts(model_path)
    if parts is None:
        return None
    path = model_path.with_name(f"{parts[0]}_replay_buffer_{parts[1]}_steps.pkl")
    return path if path.is_file() else None


def keep_transitions(callbacks: list[Any], model: Any, trained_agent: str | None) -> None:
    """For an online fine-tuning: its checkpoints keep the online transitions too, and ``-i CHECKPOINT``
    (``trained_agent``) continues with those saved beside it, unless the zoo loaded a ``replay_buffer.pkl`` there."""
    if getattr(model, "online_fraction", None) is None:
        return
    for callback in callbacks:
        if isinstance(callback, CheckpointCallback):
            callback.save_replay_buffer = True
    if trained_agent:
        load_checkpoint_buffer(model, Path(trained_agent))


def load_checkpoint_buffer(model: Any, model_path: Path) -> None:
    """Continue from a checkpoint with the transitions saved beside it, unless the zoo loaded ``replay_buffer.pkl``."""
    buffer = checkpoint_buffer(model_path)
    if buffer is not None and not model_path.with_name("replay_buffer.pkl").is_file():
        print(f"Loading the replay buffer of the checkpoint: {buffer}")
        model.load_replay_buffer(buffer)


def damaged_model(model_path: Path) -> str | None:
    """Why the model at ``model_path`` cannot be loaded (a copy or a save cut short), naming the newest checkpoint
    beside it that opens, the one to continue from; None where it opens."""
    problem = saved_model_problem(model_path)
    if problem is None:
        return None
    checkpoints = sorted(((parts[1], path) for path in model_path.parent.glob("rl_model_*_steps.zip")
                          if path != model_path and (parts := checkpoint_parts(path)) is not None), reverse=True)  # fmt: skip
    good = next((path for _, path in checkpoints if saved_model_problem(path) is None), None)
    beside = f"the last good checkpoint beside it is {good}" if good else "no checkpoint beside it opens"
    return f"{model_path} cannot be loaded: {problem}; {beside}"


def checked_model_path(get_model_path: Any) -> Any:
    """The zoo's ``get_model_path`` (the model that enjoy.py and record_video.py load), ending the command on
    :func:`damaged_model`'s line where the model cannot be loaded."""

    @functools.wraps(get_model_path)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        found = get_model_path(*args, **kwargs)
        damaged = damaged_model(Path(found[1]))
        if damaged is not None:
            fail(damaged, f"python -m rl_zoo3.{Path(sys.argv[0]).stem}")
        return found

    wrapper._sb3_cql_wrapped = True  # type: ignore[attr-defined]
    return wrapper
