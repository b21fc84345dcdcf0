"""A run's folder, claimed with ``os.mkdir``: the zoo numbers a run as it starts (the highest number there + 1) and
makes its folder with ``exist_ok``, so that two runs started together would write into one; and removed again when
the run ends before its first model, for the next run to take its number."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path
from typing import Any


def claim_run_folder(manager: Any) -> Path:
    """Make ``manager.save_path`` with ``os.mkdir``, which fails where it exists: a run started at the same moment
    took the number first, and this one takes the next free number, with ``save_path`` and ``params_path`` moved."""
    folder = Path(manager.save_path)
    folder.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            folder.mkdir()
            return folder
        except FileExistsError:
            numbered = re.fullmatch(rf"{re.escape(str(manager.env_name))}_(\d+)(.*)", folder.name)
            if numbered is None:
                raise
            manager.save_path = os.path.join(manager.log_path, f"{manager.env_name}_{int(numbered[1]) + 1}{numbered[2]}")
            manager.params_path = f"{manager.save_path}/{manager.env_name}"
            folder = Path(manager.save_path)


def remove_model_less_folder(folder: Path | None) -> Path | None:
    """Remove the run folder ``folder`` (the one this run claimed, if any) if it holds no model (``.zip``) yet;
    return it then."""
    if folder is None or not folder.is_dir() or any(folder.rglob("*.zip")):
        return None
    shutil.rmtree(folder, ignore_errors=True)
    return folder
