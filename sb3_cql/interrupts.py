"""Ctrl-C and SIGTERM in the package's command lines: one line and the shell's status, never a traceback, from the
first line of the program on (its start-up imports take seconds: torch, PyBullet, SB3).

``python -m`` imports a command's packages before it runs the command's module: the package's ``__init__`` calls
:func:`quiet_command_startup`, which quiets the start-up of the :data:`COMMANDS`, and each of them calls
:func:`started` once its imports are done; from then on Ctrl-C is Python's ``KeyboardInterrupt`` again, for the
command to end on its own line.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

#: The shell's exit status of a program ended by Ctrl-C (128 + SIGINT) and by SIGTERM (128 + SIGTERM).
INTERRUPTED_STATUS = 128 + signal.SIGINT
TERMINATED_STATUS = 128 + signal.SIGTERM


#: The package's command lines (``python -m MODULE``), each of which calls :func:`started` after its imports.
COMMANDS = ("sb3_cql.data", "sb3_cql.evaluate", "sb3_cql.protocol", "sb3_cql.benchmark")


def quiet_command_startup() -> None:
    """:func:`quiet_startup` if this process is ``python -m`` one of :data:`COMMANDS` still importing its packages
    (``sys.argv[0]`` is ``-m`` until the module runs); nothing otherwise."""
    argv = getattr(sys, "orig_argv", None) or []
    if getattr(sys, "argv", [""])[:1] != ["-m"] or "-m" not in argv[:-1]:
        return
    module = argv[argv.index("-m") + 1]
    module = module.removesuffix(".__main__")
    if module in COMMANDS:
        quiet_startup(f"python -m {module}")


def quiet_startup(prog: str) -> None:
    """Until :func:`started`, Ctrl-C or SIGTERM ends the program with one line (``PROG: interrupted while starting``)
    and status 130 or 143: nothing has been done that could be kept. Only the main thread can set handlers."""

    def end(signum: int, frame: Any) -> None:
        sys.stderr.write(f"{prog}: interrupted while starting: nothing done\n")
        sys.stderr.flush()
        os._exit(INTERRUPTED_STATUS if signum == signal.SIGINT else TERMINATED_STATUS)

    signal.signal(signal.SIGINT, end)
    if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
        signal.signal(signal.SIGTERM, end)


def started() -> None:
    """Ctrl-C raises ``KeyboardInterrupt`` again, and SIGTERM its default action, for the command to handle."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def terminate_as_interrupt() -> None:
    """SIGTERM raises ``KeyboardInterrupt`` as Ctrl-C does (a ``kill PID`` then ends the command as Ctrl-C would,
    keeping what it keeps), marked ``terminated`` for the exit status :func:`exit_status` gives."""

    def interrupt(signum: int, frame: Any) -> None:
        error = KeyboardInterrupt()
        error.terminated = True  # type: ignore[attr-defined]
        raise error

    signal.signal(signal.SIGTERM, interrupt)


def exit_status(interrupt: BaseException) -> int:
    """130 for Ctrl-C, 143 for a SIGTERM that :func:`terminate_as_interrupt` turned into ``interrupt``."""
    return TERMINATED_STATUS if getattr(interrupt, "terminated", False) else INTERRUPTED_STATUS


#: prctl's option: the signal this process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int) -> None:
    """Linux: have the kernel kill this process (``SIGKILL``) when its parent dies, so that a killed command takes
    its worker processes along instead of leaving them waiting or writing beside a new run. ``parent``: the
    expected parent's pid (exit now if it is already gone). Elsewhere nothing."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # it died before the prctl
        os._exit(1)


def run_command(main: Any) -> None:
    """Run a command line's ``main()`` as one of :data:`COMMANDS` runs it: Ctrl-C raises ``KeyboardInterrupt`` again
    (:func:`started`) and SIGTERM too (:func:`terminate_as_interrupt`), for ``main`` to say what it kept; once it
    returns or fails, a second Ctrl-C while the program exits prints no traceback either."""
    started()
    terminate_as_interrupt()
    try:
        main()
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (and a SIGTERM that has a handler) back while the block runs, so that what it does is done whole
    (a gradient step: every optimiser of the model steps, or none), then act as the first one would have: its handler
    (Python's raises ``KeyboardInterrupt``) runs once the block is done. A signal ignored, or left to its default
    action, is not held; only the main thread receives signals: in another one, the block just runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    held = {signum: handler for signum, handler in previous.items() if callable(handler)}
    received: list[tuple[int, Any]] = []
    for signum in held:
        signal.signal(signum, lambda signum, frame: received.append((signum, frame)))
    try:
        yield
    finally:
        for signum, handler in held.items():
            signal.signal(signum, handler)
    if received:
        signum, frame = received[0]
        held[signum](signum, frame)
