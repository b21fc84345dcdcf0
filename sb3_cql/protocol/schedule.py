"""The protocol's schedule: every unit of work not yet recorded (:mod:`~sb3_cql.protocol.runner`'s trainings,
fine-tunings and evaluations), run on local worker processes or Ray tasks, a finished training's evaluations first,
one protocol process per results folder."""

from __future__ import annotations

import fcntl
import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, wait
from contextlib import contextmanager
from typing import Any

from sb3_cql.processes import WorkerPool
from sb3_cql.protocol.records import FINETUNE_ROW, ResultsFolder, system_info, write_json
from sb3_cql.protocol.runner import SCRIPTED, Protocol, ProtocolError, UnitsFailed, evaluate, fine_tunes, train

#: Environment variables of the command that the protocol's Ray tasks see too (a node's own otherwise).
RAY_TASK_ENV = ("MINARI_DATASETS_PATH", "MPLBACKEND")


@contextmanager
def _units_executor(protocol: Protocol) -> Iterator[tuple[Any, int]]:
    """Where the protocol's units run, and how many at a time: ``protocol.workers`` local processes
    (:class:`~sb3_cql.processes.WorkerPool`: they die with the runner, and Ctrl-C ends them at once), or with
    ``protocol.ray_address`` Ray tasks of one CPU each, as many at a time as the cluster has CPUs unless ``workers``
    says otherwise (a task whose worker or node died runs again, from its checkpoints)."""
    if protocol.ray_address is None:
        with WorkerPool(protocol.workers) as pool:
            yield pool, protocol.workers
        return
    from sb3_cql.cluster import ClusterError, RayExecutor

    env_vars = {name: os.environ[name] for name in RAY_TASK_ENV if name in os.environ}
    try:
        executor = RayExecutor(protocol.ray_address, num_cpus=1, env_vars=env_vars)
    except ClusterError as error:
        raise ProtocolError(str(error)) from None
    with executor:
        yield executor, protocol.workers if protocol.workers > 1 else executor.cpus


def _seconds(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m{seconds:02d}s" if hours else f"{minutes}m{seconds:02d}s"


#: A unit of work waiting for a worker: its name for the log, the function, its arguments.
Unit = tuple[tuple[str, ...], Callable[..., dict[str, Any]], tuple[Any, ...]]


@contextmanager
def _exclusive(results: ResultsFolder) -> Iterator[None]:
    """One protocol process per results folder at a time."""
    results.root.mkdir(parents=True, exist_ok=True)
    with open(results.root / ".lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ProtocolError(f"another python -m sb3_cql.protocol is working in {results.root}") from None
        yield


def run_protocol(protocol: Protocol) -> dict[str, int]:
    """Do every unit of ``protocol`` not yet recorded, ``protocol.workers`` at a time, printing one line per unit;
    return the counts of units ``done`` now, ``skipped`` (recorded before) and ``failed``.

    :raises UnitsFailed: after the other units, if any failed.
    """
    protocol.check()
    results = protocol.results
    counts = {"done": 0, "skipped": 0, "failed": 0}
    failures: list[str] = []
    threads = 1 if protocol.workers > 1 or protocol.ray_address is not None else None
    with _exclusive(results):
        protocol.settings.check_folder(results)
        system = results.root / "system.json"
        if not system.is_file():
            write_json(system, system_info())
        with _units_executor(protocol) as (pool, slots):
            # Units wait here, not in the pool's own (first in, first out) queue, so that a finished training's
            # evaluations go first: its results come as soon as possible, not after every other training.
            waiting: deque[Unit] = deque()
            pending: dict[Future, tuple[str, ...]] = {}

            def evaluations(algo: str, seed: int) -> list[Unit]:
                units = []
                for task in protocol.tasks:
                    name = ("eval", algo, f"seed {seed}", task)
                    if results.evaluation_record(algo, seed, task).is_file():
                        counts["skipped"] += 1
                        print(f"[{' '.join(name)}] skipped: recorded", flush=True)
                    else:
                        units.append((name, evaluate, (protocol, algo, seed, task, threads)))
                return units

            def finetunings(algo: str, seed: int) -> list[Unit]:
                units = []
                for task in protocol.finetune if fine_tunes(algo) else []:
                    row = FINETUNE_ROW.format(algo=algo, task=task)
                    if results.training_record(row, seed).is_file():
                        counts["skipped"] += 1
                        print(f"[finetune {algo} seed {seed} {task}] skipped: recorded", flush=True)
                        units += evaluations(row, seed)
                    else:
                        units.append((("finetune", algo, f"seed {seed}", task), train, (protocol, algo, seed, threads, task)))
                return units

            def submit() -> None:
                while waiting and len(pending) < slots:
                    name, function, arguments = waiting.popleft()
                    pending[pool.submit(function, *arguments)] = name

            for seed in protocol.seeds:
                for algo in protocol.algos:
                    if algo in SCRIPTED or results.training_record(algo, seed).is_file():
                        if algo not in SCRIPTED:
                            counts["skipped"] += 1
                            print(f"[train {algo} seed {seed}] skipped: recorded", flush=True)
                        waiting.extend(evaluations(algo, seed))
                        if algo not in SCRIPTED:
                            waiting.extend(finetunings(algo, seed))
                    else:
                        print(f"[train {algo} seed {seed}] queued, log {results.training_log(algo, seed)}", flush=True)
                        waiting.append((("train", algo, f"seed {seed}"), train, (protocol, algo, seed, threads)))
            submit()
            while pending:
                finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    name = pending.pop(future)
                    label = f"[{' '.join(name)}]"
                    error = future.exception()
                    if error is not None:
                        counts["failed"] += 1
                        failures.append(f"{label} {error}")
                        print(f"{label} FAILED: {error}", flush=True)
                        continue
                    counts["done"] += 1
                    record = future.result()
                    if name[0] in ("train", "finetune"):
                        rate = record["best_eval_success_rate"]
                        best = "no evaluation" if rate is None else f"best evaluation {rate:.3f}"
                        wall = _seconds(record["train_wall_time_s"])
                        print(f"{label} done: {record['training_steps']} steps in {len(record['segments'])} segment(s), "
                              f"{best} at step {record['best_step']}, {wall}", flush=True)  # fmt: skip
                        then = evaluations(record["algo"], record["seed"])
                        if name[0] == "train":
                            then += finetunings(record["algo"], record["seed"])
                        waiting.extendleft(reversed(then))
                    else:
                        print(f"{label} success rate {record['success_rate']:.3f} over {record['episodes']} episodes, "
                              f"{_seconds(record['eval_wall_time_s'])}", flush=True)  # fmt: skip
                submit()
    if failures:
        raise UnitsFailed(f"{len(failures)} unit(s) failed:\n" + "\n".join(failures))
    return counts
