"""The suite passes however it is started."""

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

CHILD_TEST = """
import signal, subprocess, sys


def test_a_child_ends_on_ctrl_c():
    child = subprocess.Popen([sys.executable, "-c", "import time; print('ready', flush=True); time.sleep(60)"],
                             stdout=subprocess.PIPE, text=True)
    child.stdout.readline()
    child.send_signal(signal.SIGINT)
    assert child.wait(timeout=20) != 0
"""


def ignore_ctrl_c() -> None:
    """What a shell does for ``command &`` without job control, and a blocked SIGINT besides."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


def test_children_of_a_suite_started_with_ctrl_c_ignored_still_take_it(tmp_path):
    """A test that sends SIGINT to its child passes under a pytest started with SIGINT ignored and blocked, with the
    suite's conftest (and would time out without it: the child inherits the ignored SIGINT)."""
    (tmp_path / "test_child.py").write_text(textwrap.dedent(CHILD_TEST))
    tests = Path(__file__).resolve().parent
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider", str(tmp_path / "test_child.py")],
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(tests), os.environ.get("PYTHONPATH", "")])},
        preexec_fn=ignore_ctrl_c, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert "1 passed" in result.stdout
