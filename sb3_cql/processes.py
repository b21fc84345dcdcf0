"""Signals and child processes: Ctrl-C and SIGTERM in the package's commands (:func:`quiet_command_startup` until
:func:`started`, then ``KeyboardInterrupt``), work held back from them (:func:`interrupts_deferred`,
:func:`interrupts_noted`, :func:`interrupts_blocked`), processes that die with their parent (:func:`die_with_parent`),
and the local :class:`WorkerPool`. Imported by the package's ``__init__``: what the pool needs loads when one is made.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from functools import partial
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from concurrent.futures import Future

#: The shell's exit status of a program ended by Ctrl-C (128 + SIGINT) and by SIGTERM (128 + SIGTERM).
INTERRUPTED_STATUS = 128 + signal.SIGINT
TERMINATED_STATUS = 128 + signal.SIGTERM
#: The package's command lines (``python -m MODULE``), each of which calls :func:`started` after its imports.
COMMANDS = ("sb3_cql.data", "sb3_cql.evaluate", "sb3_cql.protocol")
#: The signals that stop a command as Ctrl-C does: SIGINT and SIGTERM (``kill PID``).
INTERRUPTS = (signal.SIGINT, signal.SIGTERM)
#: prctl's option: the signal this process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


# Commands ------------------------------------------------------------------------------------------------------------


def quiet_command_startup() -> None:
    """:func:`quiet_startup` if this process is ``python -m`` one of :data:`COMMANDS` still importing its packages
    (``sys.argv[0]`` is ``-m`` until the module runs)."""
    argv = getattr(sys, "orig_argv", None) or []
    if getattr(sys, "argv", [""])[:1] != ["-m"] or "-m" not in argv[:-1]:
        return
    module = argv[argv.index("-m") + 1].removesuffix(".__main__")
    if module in COMMANDS:
        quiet_startup(f"python -m {module}")


def quiet_startup(prog: str) -> None:
    """Until :func:`started`, Ctrl-C or SIGTERM ends the program with one line and status 130 or 143."""

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


def keyboard_interrupt(signum: int) -> KeyboardInterrupt:
    """The ``KeyboardInterrupt`` a signal of :data:`INTERRUPTS` raises; a SIGTERM's is marked ``terminated``."""
    interrupt = KeyboardInterrupt()
    if signum == signal.SIGTERM:
        interrupt.terminated = True  # type: ignore[attr-defined]
    return interrupt


def terminate_as_interrupt() -> None:
    """SIGTERM raises ``KeyboardInterrupt`` as Ctrl-C does, marked ``terminated`` (:func:`keyboard_interrupt`)."""

    def interrupt(signum: int, frame: Any) -> None:
        raise keyboard_interrupt(signum)

    signal.signal(signal.SIGTERM, interrupt)


def exit_status(interrupt: BaseException) -> int:
    """130 for Ctrl-C, 143 for a SIGTERM that :func:`terminate_as_interrupt` turned into ``interrupt``."""
    return TERMINATED_STATUS if getattr(interrupt, "terminated", False) else INTERRUPTED_STATUS


def run_command(main: Any) -> None:
    """Run a command's ``main()`` with Ctrl-C and SIGTERM raising ``KeyboardInterrupt``; once it returns or fails,
    Ctrl-C is ignored while the program exits."""
    started()
    terminate_as_interrupt()
    try:
        main()
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


# Work held back ------------------------------------------------------------------------------------------------------


def _taken(signum: int, handler: Any, sigterm_as_interrupt: bool) -> bool:
    """Whether a signal with ``handler`` is held or noted: one with a handler, and with ``sigterm_as_interrupt`` a
    SIGTERM left to its default action."""
    return callable(handler) or (sigterm_as_interrupt and signum == signal.SIGTERM and handler == signal.SIG_DFL)


def _act_as_before(signum: int, handler: Any, frame: Any) -> None:
    """What ``signum`` does with ``handler``: call it, or raise :func:`keyboard_interrupt` for a default one."""
    if callable(handler):
        handler(signum, frame)
    elif handler == signal.SIG_DFL:
        raise keyboard_interrupt(signum)


@contextlib.contextmanager
def interrupts_deferred(reraise: bool = True, sigterm_as_interrupt: bool = False) -> Iterator[None]:
    """Hold Ctrl-C (and a SIGTERM that has a handler) back while the block runs, so that what it does is done whole,
    then act on the first one as its handler would have. Only the main thread receives signals: elsewhere the block
    just runs.

    :param reraise: act on the first signal held after the block; ``False``: drop them.
    :param sigterm_as_interrupt: hold a SIGTERM left to its default action too, raised afterwards as a
        ``KeyboardInterrupt`` marked ``terminated``.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in INTERRUPTS}
    held = {signum: handler for signum, handler in previous.items() if _taken(signum, handler, sigterm_as_interrupt)}
    received: list[tuple[int, Any]] = []
    for signum in held:
        signal.signal(signum, lambda signum, frame: received.append((signum, frame)))
    try:
        yield
    finally:
        for signum, handler in held.items():
            signal.signal(signum, handler)
    if received and reraise:
        signum, frame = received[0]
        _act_as_before(signum, held[signum], frame)


@contextlib.contextmanager
def interrupts_noted(sigterm_as_interrupt: bool = False) -> Iterator[Callable[[], int]]:
    """Act on Ctrl-C as its handler does, and note it: the block gets a function giving the first signal noted, 0 for
    none, so a loop still stops where Python drops the ``KeyboardInterrupt`` (raised in a ``__del__``, as PyBullet's
    ``BulletClient`` disconnects). ``sigterm_as_interrupt`` as :func:`interrupts_deferred`'s."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: 0
        return
    noted: list[int] = []
    previous = {signum: signal.getsignal(signum) for signum in INTERRUPTS}
    taken = {signum: handler for signum, handler in previous.items() if _taken(signum, handler, sigterm_as_interrupt)}

    def note(signum: int, frame: Any) -> None:
        noted.append(signum)
        _act_as_before(signum, taken[signum], frame)

    for signum in taken:
        signal.signal(signum, note)
    try:
        yield lambda: noted[0] if noted else 0
    finally:
        for signum, handler in taken.items():
            signal.signal(signum, handler)


@contextlib.contextmanager
def interrupts_blocked() -> Iterator[None]:
    """Block :data:`INTERRUPTS` in this thread while the block runs (POSIX): processes started meanwhile inherit the
    block, and a signal arriving meanwhile is delivered after it."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, set(INTERRUPTS))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


# Child processes -----------------------------------------------------------------------------------------------------


def die_with_parent(parent: int) -> None:
    """Linux: have the kernel kill this process when its parent ``parent`` dies (exit now if it is already gone)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # it died before the prctl
        os._exit(1)


def child_command() -> Callable[[], None]:
    """A ``preexec_fn`` for :mod:`subprocess`: the command takes Ctrl-C and SIGTERM at their default actions (a
    :class:`WorkerPool` worker ignores them) and dies with this process."""
    return partial(_start_child_command, os.getpid())


def _start_child_command(parent: int) -> None:
    for signum in INTERRUPTS:
        signal.signal(signum, signal.SIG_DFL)
    die_with_parent(parent)


def _start_worker(parent: int, initializer: Callable[..., Any] | None, initargs: tuple[Any, ...]) -> None:
    """Set up a :class:`WorkerPool` worker: it dies with ``parent`` and ignores Ctrl-C and SIGTERM (the parent stops
    its workers), then ``initializer``."""
    die_with_parent(parent)
    for signum in INTERRUPTS:
        signal.signal(signum, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, set(INTERRUPTS))
    if initializer is not None:
        initializer(*initargs)


class WorkerPool:
    """``workers`` spawned worker processes, a ``concurrent.futures`` executor (a killed worker fails the pending
    futures instead of hanging them). Each dies with this process and ignores Ctrl-C and SIGTERM; leaving the ``with``
    block waits for them, leaving it by an exception kills them at once.

    :param workers: worker processes.
    :param initializer: called in each worker once it is set up, with ``initargs`` (what its tasks share).
    :param initargs: the arguments of ``initializer``.
    """

    def __init__(self, workers: int, initializer: Callable[..., Any] | None = None, initargs: tuple[Any, ...] = ()) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        context = multiprocessing.get_context("spawn")
        self._executor = ProcessPoolExecutor(workers, context, _start_worker, (os.getpid(), initializer, initargs))

    def submit(self, function: Callable[..., Any], *args: Any) -> Future:
        """Run ``function(*args)`` in a worker (a worker started here inherits the block of the interrupts)."""
        with interrupts_blocked():
            return self._executor.submit(function, *args)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc_info: Any) -> None:
        if kind is None:
            self._executor.shutdown(wait=True)
            return
        with interrupts_deferred(reraise=False, sigterm_as_interrupt=True):
            self._kill()

    def _kill(self) -> None:
        """Kill the workers, then wait for the executor to fail the pending futures and close its pipes. No future is
        cancelled first: Python 3.11's executor thread raises InvalidStateError on one when it finds its workers gone.

        A worker killed halfway through sending a result (one larger than a pipe's buffer) would leave the executor's
        thread waiting for the rest of it forever, since this process holds the results pipe's writing end too: once
        the workers are dead, that end is closed here, and the thread reads the end of the pipe instead. Likewise a
        task that no dead worker will read no longer holds up the shutdown."""
        processes = list((getattr(self._executor, "_processes", None) or {}).values())
        for process in processes:
            process.kill()
        for process in processes:
            process.join()
        result_queue = getattr(self._executor, "_result_queue", None)
        if result_queue is not None:
            result_queue._writer.close()
        call_queue = getattr(self._executor, "_call_queue", None)
        if call_queue is not None:
            call_queue.cancel_join_thread()
        self._executor.shutdown(wait=True)
