"""Files that are whole or absent: the package's one atomic write (:func:`replace_atomically`), which the datasets,
the protocol's records, an evaluation's ``--output`` and model saves go through: a kill, an error or a power cut at
any instant leaves the old file or the new one, whole. Standard library only: the commands import it before torch.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import Any


def temporary_path(path: Path) -> Path:
    """The temporary name a write of ``path`` goes to: hidden, beside it, for this write alone, and ending in ``.tmp``
    (SB3 adds no suffix to it, and nothing that looks for models or episode files takes one a kill left behind)."""
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")


def sync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename in it) to disk, where the platform can."""
    with contextlib.suppress(OSError):
        descriptor = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(descriptor)
        finally:
            os.close(descriptor)


def replace_atomically(
    path: str | os.PathLike, write: Callable[[Path], Any], before_rename: Callable[[], Any] | None = None
) -> None:
    """Make ``path`` the file that ``write(temporary)`` writes, whole or not at all: ``write`` writes a temporary file
    in the same folder (missing folders are made), which is flushed to disk, renamed over ``path``, and the folder
    flushed; ``before_rename`` (a test's crash point) is called just before the rename. Whatever stops it, the
    temporary file is removed; an ``OSError`` of the write names ``path`` (not the temporary file), unchained."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    temporary = temporary_path(final)
    try:
        write(temporary)
        with open(temporary, "rb") as file:
            os.fsync(file.fileno())
        if before_rename is not None:
            before_rename()
        os.replace(temporary, final)
    except BaseException as error:
        with contextlib.suppress(OSError):  # (a read-only file system refuses even to unlink a missing file)
            temporary.unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno is not None and error.filename in (None, str(temporary)):
            raise OSError(error.errno, error.strerror or str(error), str(final)) from None  # the file asked for, not ours
        raise
    sync_folder(final.parent)


def write_atomically(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` through :func:`replace_atomically`, with the umask's permissions."""
    content = data.encode() if isinstance(data, str) else data

    def write(temporary: Path) -> None:
        with open(temporary, "xb") as file:
            file.write(content)

    replace_atomically(path, write)


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as JSON to ``path`` through :func:`write_atomically`; NaN and infinities are refused
    (``ValueError``): they are not JSON."""
    write_atomically(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


#: The causes of a write that fails for want of room (a full disk, a quota, a file size limit), and of one that fails
#: because the place cannot be written (a read-only file system, permissions).
NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
NOT_WRITABLE = (errno.EROFS, errno.EACCES, errno.EPERM)


def os_error_line(error: OSError, where: str | os.PathLike | None = None, folder_option: str = "") -> str:
    """One line for an ``OSError`` of a command: the file (``where`` when the error names none), the cause and, for a
    full disk or a place that cannot be written, what to do (``folder_option``: the option giving the folder)."""
    name = error.filename if error.filename is not None else where
    cause = error.strerror or str(error) or type(error).__name__
    if error.errno in NO_ROOM:
        return f"cannot write {name} ({cause}): free some disk space, or write to another disk, and run the command again"
    if error.errno in NOT_WRITABLE:
        where_to = f"give {folder_option} a folder" if folder_option else "write to a folder"
        return f"cannot write {name} ({cause}): {where_to} this user may write in"
    return f"{name}: {cause}" if name is not None else cause
