"""Model and replay-buffer files that are whole or absent: SB3 writes a save in place, so that a kill during it leaves
a truncated file (a ``.zip`` no load opens); here a save goes to a temporary file beside the target, then is renamed
over it."""

from __future__ import annotations

import functools
import os
import secrets
import warnings
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any


def sb3_save_path(path: str | os.PathLike, suffix: str) -> Path:
    """The file SB3 writes a save to ``path`` in: ``path`` with ``.suffix`` added when it has none (``rl_model_400_steps``
    is ``rl_model_400_steps.zip``), ``path_2`` when ``path`` is a folder (with SB3's warning)."""
    final = Path(path)
    if final.suffix == "":
        final = Path(f"{final}.{suffix}")
    if final.is_dir():
        warnings.warn(f"Path '{final}' is a folder. Will save instead to {final}_2", stacklevel=3)
        final = Path(f"{final}_2")
    return final


def save_atomically(save: Callable[[Any], None], path: Any, suffix: str) -> None:
    """Run the SB3 save ``save(target)`` so that the file at ``path`` is afterwards either the one it was or the new
    one, whole, whatever stops the save (an error, Ctrl-C, ``kill -9``, a power cut): the save writes a temporary file
    in the same folder, which is flushed to disk and renamed over the target.

    :param save: writes to the path (or file object) it is given, as SB3's ``save`` and ``save_replay_buffer`` do.
    :param path: a path, with SB3's rules (:func:`sb3_save_path`; missing folders are made); a file object is
        given to ``save`` as it is.
    :param suffix: SB3's suffix for a path without one: ``"zip"`` (models), ``"pkl"`` (replay buffers).
    """
    if not isinstance(path, (str, os.PathLike)):
        save(path)
        return
    final = sb3_save_path(path, suffix)
    final.parent.mkdir(parents=True, exist_ok=True)
    # A name for this save alone (two processes may save to one path), hidden and ending in .tmp: SB3 adds no suffix
    # to it, and nothing that looks for models (*.zip) takes one that a kill left behind.
    temporary = final.with_name(f".{final.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        save(temporary)
        with open(temporary, "rb") as file:
            os.fsync(file.fileno())
        os.replace(temporary, final)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


@functools.cache
def with_atomic_saves(algorithm: type) -> type:
    """A subclass of the SB3 algorithm class ``algorithm``, of the same name, whose ``save`` (and
    ``save_replay_buffer``, where it has one) write through :func:`save_atomically`."""

    def save(self: Any, path: Any, exclude: Any = None, include: Any = None) -> None:
        save_atomically(lambda target: algorithm.save(self, target, exclude, include), path, "zip")

    methods: dict[str, Any] = {"save": save, "saves_atomically": True, "__module__": algorithm.__module__,
                               "__qualname__": algorithm.__qualname__, "__doc__": algorithm.__doc__}  # fmt: skip
    if hasattr(algorithm, "save_replay_buffer"):

        def save_replay_buffer(self: Any, path: Any) -> None:
            save_atomically(lambda target: algorithm.save_replay_buffer(self, target), path, "pkl")

        methods["save_replay_buffer"] = save_replay_buffer
    return type(algorithm.__name__, (algorithm,), methods)


def saved_model_problem(path: str | os.PathLike) -> str | None:
    """Why the SB3 model file at ``path`` does not open, or ``None`` when it does: SB3 loads a zip archive whose
    members are whole (their checksums) and whose ``data`` holds the model's attributes."""
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()
            if damaged is not None:
                return f"its member {damaged} is damaged"
            if "data" not in archive.namelist():
                return "it holds no SB3 model (no data member)"
            if "policy.pth" not in archive.namelist():
                return "it holds no policy parameters (no policy.pth member)"
    except zipfile.BadZipFile:
        return "it is empty (0 bytes)" if os.path.getsize(path) == 0 else "it is truncated (not a whole zip archive)"
    except (OSError, EOFError, zlib.error) as error:
        return f"it cannot be read ({error})"
    return None
