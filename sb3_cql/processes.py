"""Signals and child processes: Ctrl-C and SIGTERM in the package's commands, work held back from them, processes that
die with their parent, and the local worker pool that the dataset collection and the protocol share.

Commands. ``python -m`` imports a command's packages before it runs the command's module: the package's
``__init__`` calls :func:`quiet_command_startup`, which quiets the start-up of the :data:`COMMANDS` (one line and the
shell's status, never a traceback, from the first line of the program on: its imports take seconds), and each of
them calls :func:`started` once its imports are done (:func:`run_command`); from then on Ctrl-C is Python's
``KeyboardInterrupt`` again, and SIGTERM too, for the command to end on its own line saying what it kept.

Work held back. :func:`interrupts_deferred` holds Ctrl-C and SIGTERM back while a block runs (a write, a gradient
step) and acts on them after it; :func:`interrupts_noted` notes one where Python could drop its
``KeyboardInterrupt``; :func:`interrupts_blocked` blocks them in the kernel while processes start.

Child processes. A :class:`WorkerPool` worker, and a command it starts (:func:`child_command`), die with their parent
(:func:`die_with_parent`): a killed command takes them along instead of leaving them to write beside a new run.

This module is imported by the package's ``__init__`` before a command's imports: what the pool needs
(``concurrent.futures``, ``multiprocessing``: a tenth of a second) loads when a pool is made.
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


def keyboard_interrupt(signum: int) -> KeyboardInterrupt:
    """The ``KeyboardInterrupt`` that a signal of :data:`INTERRUPTS` raises; a SIGTERM's is marked ``terminated``, for
    the exit status :func:`exit_status` gives."""
    interrupt = KeyboardInterrupt()
    if signum == signal.SIGTERM:
        interrupt.terminated = True  # type: ignore[attr-defined]
    return interrupt


def terminate_as_interrupt() -> None:
    """SIGTERM raises ``KeyboardInterrupt`` as Ctrl-C does (a ``kill PID`` then ends the command as Ctrl-C would,
    keeping what it keeps), marked ``terminated`` (:func:`keyboard_interrupt`)."""

    def interrupt(signum: int, frame: Any) -> None:
        raise keyboard_interrupt(signum)

    signal.signal(signal.SIGTERM, interrupt)


def exit_status(interrupt: BaseException) -> int:
    """130 for Ctrl-C, 143 for a SIGTERM that :func:`terminate_as_interrupt` turned into ``interrupt``."""
    return TERMINATED_STATUS if getattr(interrupt, "terminated", False) else INTERRUPTED_STATUS


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


# Work held back ------------------------------------------------------------------------------------------------------


def _taken(signum: int, handler: Any, sigterm_as_interrupt: bool) -> bool:
    """Whether a signal whose handler is ``handler`` is held or noted: one with a handler (Python's for Ctrl-C raises
    ``KeyboardInterrupt``), and with ``sigterm_as_interrupt`` a SIGTERM left to its default action too. A signal
    ignored, or left to its default otherwise, is not."""
    return callable(handler) or (sigterm_as_interrupt and signum == signal.SIGTERM and handler == signal.SIG_DFL)


def _act_as_before(signum: int, handler: Any, frame: Any) -> None:
    """What ``signum`` does with ``handler``: call it, or raise :func:`keyboard_interrupt` for a default one."""
    if callable(handler):
        handler(signum, frame)
    elif handler == signal.SIG_DFL:
        raise keyboard_interrupt(signum)


@contextlib.contextmanager
def interrupts_deferred(reraise: bool = True, sigterm_as_interrupt: bool = False) -> Iterator[None]:
    """Hold Ctrl-C (and a SIGTERM that has a handler) back while the block runs, so that what it does is done whole (a
    file written, a gradient step: every optimiser of the model steps, or none), then act as the first one would have
    if ``reraise``: its handler (Python's raises ``KeyboardInterrupt``) runs once the block is done.

    :param reraise: act on the first signal held after the block; ``False``: drop them (cleaning up after an
        interrupt, when more Ctrl-C change nothing).
    :param sigterm_as_interrupt: hold a SIGTERM left to its default action too (which would end the process at once,
        without a word), and raise it afterwards as a ``KeyboardInterrupt`` marked ``terminated``.

    A signal ignored, or left to its default action otherwise, is not held; only the main thread receives signals:
    in another one, the block just runs.
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
    """Act on Ctrl-C as the handler there was does (Python's raises ``KeyboardInterrupt``), and note it: the block gets
    a function giving the first signal noted, 0 for none. Python drops an exception raised in a ``__del__``
    (PyBullet's ``BulletClient`` disconnects in one, which a garbage collection can run at any moment), so a loop that
    checks the note still stops (raising :func:`keyboard_interrupt` of it).

    :param sigterm_as_interrupt: take a SIGTERM left to its default action too (which would end the process without
        a word), raising ``KeyboardInterrupt`` marked ``terminated``.

    Only the main thread receives signals; elsewhere, or with the signals ignored, nothing is noted.
    """
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
    """Block :data:`INTERRUPTS` in this thread while the block runs (POSIX; elsewhere nothing): processes started
    meanwhile inherit the block, and a signal arriving meanwhile is delivered after it."""
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
    """Linux: have the kernel kill this process (``SIGKILL``) when its parent dies, so that a killed command takes
    its worker processes along instead of leaving them waiting or writing beside a new run. ``parent``: the
    expected parent's pid (exit now if it is already gone). Elsewhere nothing."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # it died before the prctl
        os._exit(1)


def child_command() -> Callable[[], None]:
    """A ``preexec_fn`` for :mod:`subprocess`: the command takes Ctrl-C and SIGTERM as a shell would give them (their
    default actions: a :class:`WorkerPool` worker ignores them, and an ignored signal stays ignored across ``exec``)
    and dies with this process (:func:`die_with_parent`)."""
    return partial(_start_child_command, os.getpid())


def _start_child_command(parent: int) -> None:
    for signum in INTERRUPTS:
        signal.signal(signum, signal.SIG_DFL)
    die_with_parent(parent)


def _start_worker(parent: int, initializer: Callable[..., Any] | None, initargs: tuple[Any, ...]) -> None:
    """Set up a :class:`WorkerPool` worker: it dies with ``parent``, and ignores Ctrl-C and SIGTERM (no traceback from
    them: they reach every process of a terminal's group, and the parent stops its workers itself). It started with
    them blocked (:meth:`WorkerPool.submit`), so one sent before this point is dropped too. Then ``initializer``."""
    die_with_parent(parent)
    for signum in INTERRUPTS:
        signal.signal(signum, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, set(INTERRUPTS))
    if initializer is not None:
        initializer(*initargs)


class WorkerPool:
    """``workers`` local worker processes, a ``concurrent.futures`` executor (``submit`` returns a ``Future``):

    - spawned, not forked: a parent holding torch threads or a PyBullet client must not be copied, and no lock is
      inherited; an executor, not a ``multiprocessing.Pool``: a killed worker fails the pending futures with
      ``BrokenProcessPool`` instead of hanging them;
    - each worker dies with this process and ignores Ctrl-C and SIGTERM: this process stops its workers itself;
    - leaving the ``with`` block waits for the workers to end; leaving it by an exception (Ctrl-C, a failure) kills
      them at once instead, not waited for through the tasks they run (a second Ctrl-C meanwhile changes nothing),
      each taking its :func:`child_command` processes along.

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
        """Run ``function(*args)`` in a worker. Ctrl-C and SIGTERM are blocked meanwhile: a worker started here
        inherits the block until it ignores them."""
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
        """Shut the executor down without waiting for its tasks: kill its workers (they ignore SIGTERM), then wait for
        the executor to fail the pending futures and close its pipes. No future is cancelled first: in Python 3.11,
        the executor's thread raises InvalidStateError on a cancelled one when it finds its workers gone, and exiting
        before that thread is done can write to a pipe it closes (EBADF)."""
        for process in list((getattr(self._executor, "_processes", None) or {}).values()):
            process.kill()
        self._executor.shutdown(wait=True)
