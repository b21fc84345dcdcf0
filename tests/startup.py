"""Ctrl-C while a command line starts: sent once its start-up imports have begun, seen through ``/proc``."""

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest


def interrupt_while_starting(command: list[str], **popen) -> tuple[int, str]:
    """Start ``command`` in a process group of its own (as a shell runs it), send the group SIGINT (a terminal's
    Ctrl-C) as soon as numpy, among its first imports, is loaded, and return its exit status and stderr. Skips where
    there is no ``/proc`` to see it."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                               **popen)  # fmt: skip
    maps = Path(f"/proc/{process.pid}/maps")
    if not maps.exists():
        process.kill()
        pytest.skip("needs /proc to see when the start-up imports begin")
    deadline = time.monotonic() + 60
    while "_multiarray_umath" not in maps.read_text():
        assert process.poll() is None and time.monotonic() < deadline, "the command ended before its imports"
        time.sleep(0.01)
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    return process.returncode, stderr
