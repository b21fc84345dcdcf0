"""Running the package's independent units of work (collection chunks, the protocol's trainings and evaluations) on a
Ray cluster: ``--ray ADDRESS`` of ``python -m sb3_cql.data collect`` and ``python -m sb3_cql.protocol``. Ray is an
optional extra (``pip install -e ".[ray]"``), needed with this package on every node (docs: *Running on a cluster*).
"""

from __future__ import annotations

import contextlib
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from typing import Any

#: How to install Ray, for the line a ``--ray`` without it gives.
INSTALL = 'pip install -e ".[ray]" (or pip install "ray>=2.60")'
#: Tasks in flight per CPU of the cluster: enough for every CPU to find its next task while results come back.
TASKS_PER_CPU = 2
#: Seconds a connection to a cluster's address may take before it counts as out of reach.
PROBE_TIMEOUT_S = 5.0


class ClusterError(RuntimeError):
    """Ray is not installed, or the cluster cannot be reached."""


def connect(address: str) -> Any:
    """Connect this process to the Ray cluster at ``address`` (``auto``: the cluster this machine belongs to; a
    ``ray://host:port`` client address or a ``host:port`` one otherwise) once, and return the ``ray`` module."""
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--ray needs Ray, which is not installed: {INSTALL}") from None
    if not ray.is_initialized():
        check_address(address)
        try:
            ray.init(address=address, logging_level="ERROR", log_to_driver=False, configure_logging=True)
        except Exception as error:  # Ray raises ConnectionError, ValueError or its own errors
            raise ClusterError(f"cannot connect to the Ray cluster at {address}: {' '.join(str(error).split())}") from None
    return ray


def check_address(address: str) -> None:
    """A :class:`ClusterError` within seconds where no Ray cluster answers at ``address`` (:func:`_unreachable`):
    ``ray.init`` would wait for minutes."""
    unreachable = _unreachable(address)
    if unreachable is not None:
        raise ClusterError(f"cannot connect to the Ray cluster at {address}: {unreachable}; start it (ray start --head) "
                           "or give the address that ray status prints")  # fmt: skip


def _unreachable(address: str) -> str | None:
    """Why no Ray cluster can be connected to at a ``host:port`` or ``ray://host:port`` address, found within
    :data:`PROBE_TIMEOUT_S` seconds: nothing answers, or something that is not Ray (a web server, Ray's dashboard).
    Ray speaks gRPC (HTTP/2): the probe sends HTTP/2's preface and an empty SETTINGS frame, which a gRPC server answers
    with a SETTINGS frame. ``None`` where it does, or for ``auto``, or with TLS (``RAY_USE_TLS``)."""
    import os
    import socket

    host, separator, port = address.removeprefix("ray://").rpartition(":")
    if not separator or not port.isdigit() or not host:
        return None
    try:
        connection = socket.create_connection((host.strip("[]"), int(port)), timeout=PROBE_TIMEOUT_S)
    except OSError as error:
        return f"nothing answers at {host}:{port} ({error.strerror or error})"
    if os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
        connection.close()
        return None
    with connection:
        try:
            connection.sendall(HTTP2_PREFACE)
            answer = b""
            while len(answer) < 9 and (more := connection.recv(9 - len(answer))):
                answer += more
        except OSError as error:  # a timeout, a reset
            answer = f"({error.strerror or type(error).__name__})".encode()
    if len(answer) == 9 and answer[3] == HTTP2_SETTINGS:
        return None
    what = "a web server" if answer.startswith((b"HTTP/", b"<")) else "something that does not speak gRPC"
    return (f"{what} answers at {host}:{port}, not Ray (the address of its GCS, 6379 by default, or ray:// and its "
            "client server's, 10001; not its dashboard's)")  # fmt: skip


#: HTTP/2's client connection preface and an empty SETTINGS frame (RFC 9113, 3.4 and 6.5).
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
#: The type of HTTP/2's SETTINGS frame, the first a server sends.
HTTP2_SETTINGS = 4


def cluster_cpus(ray: Any) -> int:
    """The CPUs of the connected cluster (1 at least)."""
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


def run_in_order(
    function: Callable[..., Any], arguments: Iterable[tuple[Any, ...]], address: str, num_cpus: float = 1, **options: Any
) -> Iterator[Any]:
    """The results of ``function(*args)`` for each ``args`` of ``arguments``, in their order, each call a Ray task with
    ``num_cpus`` CPUs on the cluster at ``address`` (retried by Ray if its node dies: ``max_retries`` in
    ``options``). At most :data:`TASKS_PER_CPU` tasks a cluster CPU are in flight; the ones left when the caller stops
    (or fails) are cancelled."""
    ray = connect(address)
    remote = ray.remote(num_cpus=num_cpus, **options)(function)
    pending = iter(arguments)
    limit = TASKS_PER_CPU * max(1, int(cluster_cpus(ray) // max(num_cpus, 1e-9)))
    in_flight: deque = deque()
    try:
        for args in pending:
            in_flight.append(remote.remote(*args))
            if len(in_flight) >= limit:
                break
        while in_flight:
            result = ray.get(in_flight.popleft())
            for args in pending:  # keep the cluster busy while this result is used
                in_flight.append(remote.remote(*args))
                break
            yield result
    finally:
        for reference in in_flight:
            with contextlib.suppress(Exception):
                ray.cancel(reference, force=True)


class RayExecutor:
    """A ``concurrent.futures`` executor whose calls are Ray tasks on the cluster at ``address``, each with
    ``num_cpus`` CPUs, the environment variables ``env_vars`` and Ray's retries of a task whose worker or node died
    (``max_retries``): ``submit`` returns the task's ``Future``, and the exception of a failed call is the function's
    own (not Ray's wrapper). Leaving the ``with`` block cancels the tasks still running."""

    def __init__(self, address: str, num_cpus: float = 1, env_vars: dict[str, str] | None = None, max_retries: int = 3):
        self.ray = connect(address)
        self.options: dict[str, Any] = {"num_cpus": num_cpus, "max_retries": max_retries}
        if env_vars:
            self.options["runtime_env"] = {"env_vars": dict(env_vars)}
        self._references: list[Any] = []

    @property
    def cpus(self) -> int:
        """The cluster's CPUs."""
        return cluster_cpus(self.ray)

    def submit(self, function: Callable[..., Any], *args: Any) -> Future:
        reference = self.ray.remote(**self.options)(function).remote(*args)
        self._references.append(reference)
        future: Future = Future()
        reference.future().add_done_callback(lambda done: _settle(future, done))
        return future

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        for reference in self._references:
            with contextlib.suppress(Exception):
                self.ray.cancel(reference, force=True)


def _settle(future: Future, done: Future) -> None:
    """Give ``future`` the result of Ray's ``done``, or the exception its task raised (Ray wraps it: its ``cause``)."""
    error = done.exception()
    if error is None:
        future.set_result(done.result())
    else:
        future.set_exception(getattr(error, "cause", None) or error)
