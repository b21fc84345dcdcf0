"""Collect behaviour-policy rollouts (:mod:`sb3_cql.data.rollouts`) into Minari datasets, in parallel, resumably and
atomically: :func:`collect_dataset`, :func:`ensure_dataset` (a standard dataset, collected where it is missing) and
:func:`mix_datasets`. The workers die with the parent (:class:`sb3_cql.processes.WorkerPool`); the files a collection
writes, and why a kill at any instant loses nothing kept, are :mod:`sb3_cql.data.store`'s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import sys
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import gymnasium as gym
import numpy as np
from minari import MinariDataset
from minari.data_collector import EpisodeBuffer
from tqdm import tqdm

from sb3_cql.data import assembly, ids
from sb3_cql.data.assembly import assemble, collection_metadata
from sb3_cql.data.errors import DatasetError
from sb3_cql.data.estimates import check_space, estimate, plan
from sb3_cql.data.ids import POLICIES, RANDOM_POLICY
from sb3_cql.data.rollouts import CollectionSpec, _init_worker, _run_episode, _run_episodes, _worker, make_policy
from sb3_cql.data.store import DatasetFiles, load_dataset, other_collection, prepare_folder
from sb3_cql.processes import WorkerPool, interrupts_deferred, interrupts_noted, keyboard_interrupt

__all__ = ["CollectionSpec", "WRITE_EVERY", "collect_dataset", "ensure_dataset", "mix_datasets", "standard_collection"]

#: Episodes written to disk at a time: the most a crash (a killed process, a power cut) can lose. Ctrl-C loses none
#: of the finished ones: they are written before the collection stops.
WRITE_EVERY = 50


def _chunks(indices: list[int], size: int) -> list[list[int]]:
    """``indices`` in runs of at most ``size`` consecutive ones: the episodes of one file, one Ray task."""
    chunks: list[list[int]] = []
    for index in indices:
        if chunks and len(chunks[-1]) < size and chunks[-1][-1] == index - 1:
            chunks[-1].append(index)
        else:
            chunks.append([index])
    return chunks


def _episodes(
    spec: CollectionSpec, indices: list[int], workers: int, ray_address: str | None = None, chunk: int = WRITE_EVERY
) -> Iterator[EpisodeBuffer]:
    """The episodes ``indices`` in order, from ``workers`` processes (this one if 1), or from Ray tasks of ``chunk``
    episodes on the cluster at ``ray_address`` (a task whose node dies runs again: episodes do not depend on where)."""
    if ray_address is not None:
        from sb3_cql.cluster import run_in_order

        tasks = ((spec, indices) for indices in _chunks(indices, chunk))
        for episodes in run_in_order(_run_episodes, tasks, ray_address, num_cpus=1, max_retries=3):
            yield from episodes
        return
    if workers == 1:
        _init_worker(spec)
        try:
            yield from map(_run_episode, indices)
        finally:
            _worker["env"].close()
            _worker.clear()
        return
    try:
        # Interrupted or failed, the episodes in progress are not kept: the pool stops their workers at once.
        with WorkerPool(workers, _init_worker, (spec,)) as pool:
            # One episode a task (an episode takes 0.1 to 1 s, a task's messages ~1 ms): every episode finished in
            # order reaches this process, to be kept if the collection is interrupted.
            futures = deque(pool.submit(_run_episode, index) for index in indices)
            while futures:  # each episode let go once handed over: the collection holds no more than the workers' lead
                yield futures.popleft().result()
    except BrokenProcessPool as error:
        raise RuntimeError(
            f"a collection worker died (killed, or out of memory); the episodes written so far are kept and "
            f"running the same collection again resumes it: {error}"
        ) from error


def _resume(files: DatasetFiles, spec: CollectionSpec, overwrite: bool) -> tuple[set[int], list[bool]]:
    """The episodes (indices) an interrupted collection of ``spec`` holds, and their successes (a new collection where
    there is none); another spec's partial collection, or an unreadable file, is a :class:`DatasetError`."""
    files.check_writable()
    held_spec = files.spec()
    if files.holds_anything() and held_spec != spec.to_json():
        if not overwrite and not files.holds_no_episodes():  # one that kept none is replaced: nothing is lost
            raise DatasetError(other_collection(files, held_spec))
        shutil.rmtree(files.partial)
    if held_spec != spec.to_json():
        files.start(spec.to_json())
    files.episodes.mkdir(exist_ok=True)
    if files.storage_before_episode_files.is_dir():  # a collection written before episode files: read it into them
        episodes = files.read_storage_before_episode_files()
        for first in range(0, len(episodes), WRITE_EVERY):
            files.write_episodes(episodes[first : first + WRITE_EVERY])
        shutil.rmtree(files.storage_before_episode_files)
    held: set[int] = set()
    successes: list[bool] = []
    episode_files = files.episode_files()
    for indices, path in episode_files:
        try:
            episodes = files.read_episodes(path)
            if [episode.id for episode in episodes] != list(indices):
                raise ValueError(f"it holds episodes {[episode.id for episode in episodes]}, not {indices}")
        except Exception as error:
            readable = sum(len(other) for other, _ in episode_files) - len(indices)
            raise DatasetError(
                f"the partial collection of {files.dataset_id} in {files.partial} has a damaged file {path.name} "
                f"(episodes {indices.start}-{indices.stop - 1}: {' '.join(str(error).split()) or type(error).__name__});"
                f" its other {readable} episodes are readable: remove {path} to collect its episodes again, or pass "
                "--overwrite (overwrite=True) to start over"
            ) from None
        held.update(indices)
        successes += [bool(episode.rewards[-1] > 0) for episode in episodes]
    return held, successes


def collect_dataset(
    spec: CollectionSpec,
    dataset_id: str | None = None,
    workers: int = 1,
    overwrite: bool = False,
    progress_bar: bool = True,
    write_every: int | None = None,
    ray_address: str | None = None,
) -> MinariDataset:
    """Collect ``spec.n_episodes`` episodes into the Minari dataset ``dataset_id`` and return it.

    The episodes go to a hidden ``.partial`` folder beside the dataset, ``write_every`` at a time, each file written
    whole or not at all, then are assembled into the dataset, renamed into place (:mod:`sb3_cql.data.store`). A kill
    at any instant leaves no dataset under its id, or the complete one; the same collection run again resumes it to
    the dataset an uninterrupted run gives. A partial collection of another spec that kept episodes, or a second
    collection of the id while one runs, is a :class:`DatasetError` (``overwrite`` replaces the former). A standard
    id (:func:`standard_collection`) takes its standard collection only, or its first episodes. Actions are the
    executed ones; with noise, the policy's clean actions are in the episodes' ``infos["clean_action"]``.

    It prints (on stderr) one line before it starts: the episodes, the workers, about how long and how much disk they
    take (refused on a disk without room), or how many episodes a resumed one has. On Ctrl-C or SIGTERM, it writes
    the episodes finished, prints one line saying how many are kept, and raises the ``KeyboardInterrupt`` again.

    :param spec: what to collect.
    :param dataset_id: the Minari id; by default ``sb3cql/<env>/<policy>[-delta][-<N>k]-v0``, ``-<N>k`` for a
        number of episodes that is a multiple of 1,000 other than 10,000.
    :param workers: worker processes; the data do not depend on it.
    :param overwrite: replace an existing dataset of that id (otherwise ``FileExistsError``), and a partial
        collection of another spec.
    :param progress_bar: show episodes, transitions/s and the success rate so far.
    :param write_every: episodes written to disk at a time (``WRITE_EVERY`` by default): the most a crash loses.
    :param ray_address: run the episodes as Ray tasks of ``write_every`` episodes on the cluster at this address
        (``auto``, ``host:port`` or ``ray://host:port``) instead of ``workers`` local processes: the same dataset,
        written by this process (:mod:`sb3_cql.cluster`).
    """
    dataset_id = dataset_id or default_dataset_id(spec)
    _check_standard(spec, dataset_id)
    write_every = WRITE_EVERY if write_every is None else write_every
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if write_every < 1:
        raise ValueError(f"write_every must be >= 1, got {write_every}")
    if ray_address is not None:  # a cluster out of reach is one line before anything is written (the lock file too)
        from sb3_cql.cluster import check_address

        check_address(ray_address)
    files = DatasetFiles(dataset_id)
    with files.locked():
        files.recover()
        prepare_folder(dataset_id, overwrite)
        return _collect(spec, files, workers, overwrite, progress_bar, write_every, ray_address)


def _collect(
    spec: CollectionSpec, files: DatasetFiles, workers: int, overwrite: bool, progress_bar: bool, write_every: int,
    ray_address: str | None,
) -> MinariDataset:  # fmt: skip
    """:func:`collect_dataset` holding the dataset's lock."""
    dataset_id = files.dataset_id
    env, pending, published, held = None, [], False, 0
    try:
        env = gym.make(spec.env_id, **spec.env_kwargs)
        if spec.controller is None and spec.policy != RANDOM_POLICY:
            make_policy(spec, env)  # a model that cannot be loaded, or acts in another action mode, fails here
        # Before anything is written: a disk without room, or a cluster out of reach, is one line that leaves nothing.
        left = spec.n_episodes - (files.episodes_held() if files.spec() == spec.to_json() else 0)
        where = None
        if left > 0:
            _, _, size = estimate(spec, left, workers)
            _, _, total = estimate(spec, spec.n_episodes, workers)
            check_space(files, size + total, f"{left} episodes and the dataset's assembly")
            if ray_address is not None:
                from sb3_cql.cluster import cluster_cpus, connect

                workers = cluster_cpus(connect(ray_address))
                where = f"as Ray tasks on the {workers} CPUs of the cluster at {ray_address}"
        done, successes = _resume(files, spec, overwrite)
        held = len(done)
        missing = [index for index in range(spec.n_episodes) if index not in done]
        print(plan(spec, dataset_id, workers, held, where), file=sys.stderr, flush=True)
        steps, begin = 0, time.perf_counter()
        with (
            interrupts_noted(sigterm_as_interrupt=True) as interrupted,
            contextlib.closing(_episodes(spec, missing, workers, ray_address, write_every)) as episodes,
            tqdm(total=spec.n_episodes, initial=held, desc=dataset_id, unit="ep", disable=not progress_bar) as bar,
        ):
            for episode in episodes:
                if pending and episode.id != pending[-1].id + 1:  # a file holds consecutive episodes
                    held += _write(files, pending)
                pending.append(episode)
                successes.append(bool(episode.rewards[-1] > 0))
                steps += len(episode.rewards)
                bar.update()
                rate = steps / (time.perf_counter() - begin)
                bar.set_postfix(transitions_per_s=f"{rate:.0f}", success_rate=f"{np.mean(successes):.3f}")
                if len(pending) >= write_every:
                    held += _write(files, pending)
                if interrupted():  # a Ctrl-C whose KeyboardInterrupt Python dropped
                    raise keyboard_interrupt(interrupted())
            held += _write(files, pending)
            if interrupted():
                raise keyboard_interrupt(interrupted())
            assemble(files, env, lambda successes: collection_metadata(dataset_id, spec, successes, env))
        with interrupts_deferred(sigterm_as_interrupt=True):
            final = files.publish()
            published = True
        return MinariDataset(final / "data")
    except KeyboardInterrupt as interrupt:
        # More Ctrl-C while the finished episodes are written change nothing.
        with interrupts_deferred(reraise=False, sigterm_as_interrupt=True):
            if not published and pending:
                _write(files, pending)
            if not published:  # what the files hold (a write the interrupt came at the end of is counted too)
                held = files.episodes_held()
            print(_interrupted(dataset_id, spec, held, env is not None, published), file=sys.stderr, flush=True)
        interrupt.said = True  # type: ignore[attr-defined]  # what was kept is said: callers need not say more
        raise
    finally:
        if env is not None:
            env.close()


def _write(files: DatasetFiles, pending: list[EpisodeBuffer]) -> int:
    """Write the ``pending`` episodes as one file, whole even on Ctrl-C; empty the list; return how many."""
    with interrupts_deferred(sigterm_as_interrupt=True):
        written = len(pending)
        if pending:
            files.write_episodes(pending)
            pending.clear()
    return written


def _interrupted(dataset_id: str, spec: CollectionSpec, held: int, started: bool, published: bool) -> str:
    """The line an interrupted collection prints."""
    if published:
        return f"interrupted: {dataset_id} was already complete ({spec.n_episodes} episodes)"
    if not started:
        return f"interrupted before collecting {dataset_id}: the same command starts (or resumes) it"
    if held == spec.n_episodes:
        return f"interrupted: all {held} episodes of {dataset_id} kept; the same command assembles the dataset"
    return f"interrupted: {held} of {spec.n_episodes} episodes of {dataset_id} kept; the same command resumes"


def ensure_dataset(
    dataset_id: str, n_episodes: int | None = None, workers: int | None = None, progress_bar: bool = True
) -> MinariDataset:
    """The dataset ``dataset_id``, collected first (or resumed, as :func:`collect_dataset` does) if it is missing and
    its id is a standard one (:func:`standard_collection`); any other missing id raises
    :class:`~sb3_cql.data.DatasetError`. While another process collects it, this one waits, then loads it.

    :param dataset_id: the Minari id.
    :param n_episodes: episodes of a collection; ``None`` for :class:`CollectionSpec`'s default.
    :param workers: collection processes; by default one per CPU.
    :param progress_bar: show the collection's progress.
    """
    spec = standard_collection(dataset_id)
    if ids.dataset_exists(dataset_id) or spec is None:
        return load_dataset(dataset_id)  # an error naming the id if it is missing
    if n_episodes is not None:
        spec = dataclasses.replace(spec, n_episodes=n_episodes)
    files = DatasetFiles(dataset_id)
    if files.is_locked():
        print(f"waiting for the collection of {dataset_id} by another process (pid {files.holder()}) to end",
              file=sys.stderr, flush=True)  # fmt: skip
    with files.locked(wait=True):
        files.recover()
        if ids.dataset_exists(dataset_id):  # the other process collected it meanwhile
            return load_dataset(dataset_id)
        prepare_folder(dataset_id, overwrite=False)
        return _collect(spec, files, workers or os.cpu_count() or 1, False, progress_bar, WRITE_EVERY, None)


def standard_collection(dataset_id: str) -> CollectionSpec | None:
    """The collection a standard id stands for (``sb3cql/<task>/<policy>[-delta][-<N>k]-v0`` with a named policy
    and a registered task: its episodes, 10,000 without ``-<N>k``, from seed 0, the policy's default noise), or
    ``None`` for any other id. A ``-<N>k`` dataset holds the first episodes of the 10,000-episode one (episode ``i``
    is reset with seed ``i``)."""
    fields = ids.standard_collection_fields(dataset_id)
    return None if fields is None else CollectionSpec(**fields)


def _check_standard(spec: CollectionSpec, dataset_id: str) -> None:
    """A :class:`DatasetError` if ``dataset_id`` is a standard id and ``spec`` is not its collection or the first
    episodes of it (:func:`~sb3_cql.data.ids.standard_mismatch`): what trains on the id would get other data."""
    fields = json.loads(spec.to_json())
    mismatch = ids.standard_mismatch(dataset_id, fields, "this collection")
    if mismatch is None:
        return
    own = default_dataset_id(spec)  # the spec's own standard id, where it is one; else a custom one
    if own == dataset_id or ids.standard_mismatch(own, fields, "") is not None:
        own = dataset_id.rsplit("-v", 1)[0] + "-custom-v0"
    raise DatasetError(f"{mismatch}: give it an id of its own, e.g. --dataset-id {own}")


def default_dataset_id(spec: CollectionSpec) -> str:
    """The id a collection of ``spec`` gets without one (:func:`collect_dataset`'s ``dataset_id``)."""
    policy_name = spec.policy if spec.policy in POLICIES else Path(spec.policy).stem
    in_thousands = spec.n_episodes >= 1000 and spec.n_episodes % 1000 == 0
    return ids.dataset_id(spec.env_id, policy_name, spec.action_mode, episodes=spec.n_episodes if in_thousands else None)


def mix_datasets(source_ids: list[str], dataset_id: str, overwrite: bool = False) -> MinariDataset:
    """Combine the datasets ``source_ids`` (same env and spaces, each once) into a new dataset ``dataset_id``, not a
    standard id (whose data are its collection's), written atomically like :func:`collect_dataset`; its metadata lists
    them under ``combined_datasets`` (:func:`sb3_cql.data.assembly.mix_datasets`)."""
    repeated = sorted({source for source in source_ids if source_ids.count(source) > 1})
    if repeated:
        raise DatasetError(f"{', '.join(repeated)} given more than once: give each dataset to mix once")
    if standard_collection(dataset_id) is not None:
        raise DatasetError(f"{dataset_id} is a standard dataset id (the data of one collection, python -m sb3_cql.data "
                           f"collect): give the mix an id of its own, e.g. --dataset-id "
                           f"{dataset_id.rsplit('/', 1)[0]}/mixed-v0")  # fmt: skip
    return assembly.mix_datasets(source_ids, dataset_id, overwrite)
