"""Model and replay-buffer saves that are whole or absent (SB3 writes in place: a kill would leave a truncated
``.zip``), through :func:`sb3_cql.files.replace_atomically`, whose names this module re-exports."""

from __future__ import annotations

import functools
import os
import warnings
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sb3_cql.files import replace_atomically, sync_folder, temporary_path, write_atomically

__all__ = ["check_saved_model", "replace_atomically", "save_atomically", "saved_model_problem", "sb3_save_path", "sync_folder",
           "temporary_path", "with_atomic_saves", "write_atomically"]  # fmt: skip


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
    """Run the SB3 save ``save(target)`` so that the file at ``path`` (SB3's rules, :func:`sb3_save_path`, with
    ``suffix`` ``"zip"`` or ``"pkl"``) is afterwards either the one it was or the new one, whole, whatever stops the
    save (:func:`replace_atomically`). A file object is given to ``save`` as it is."""
    if not isinstance(path, (str, os.PathLike)):
        save(path)
        return
    replace_atomically(sb3_save_path(path, suffix), save)


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


def check_saved_model(path: Any) -> None:
    """A ``ValueError`` naming the file and what it lacks where the SB3 model zip at ``path`` (or ``path`` + ``.zip``)
    does not open (:func:`saved_model_problem`); nothing for anything else (SB3's ``load`` reports on it itself)."""
    if not isinstance(path, (str, os.PathLike)):
        return
    found = next((file for file in (Path(path), Path(f"{path}.zip")) if file.is_file()), None)
    problem = saved_model_problem(found) if found is not None and zipfile.is_zipfile(found) else None  # (SB3 names others)
    if problem is not None:
        raise ValueError(f"cannot load {found}: {problem}")
