r"""The datasets on disk: a dataset's files and lock, the recovery and publication of a replacement, and the loading
of a dataset, with a :class:`DatasetError` that names it and says how to make it.

The files of a dataset being written are laid out so that a kill at any instant loses nothing already kept. Beside a
dataset's folder ``NAME`` (Minari's, under its namespace), while it is collected or replaced:

- ``.NAME.partial/collection.json``: the collection's spec (:meth:`~sb3_cql.data.CollectionSpec.to_json`).
- ``.NAME.partial/episodes/FFFFFF-LLLLLL.pkl``: episodes ``F`` to ``L`` of the collection (their Minari
  ``EpisodeBuffer``\ s). Every file is written under a temporary name, flushed to disk and renamed, so a file there
  is complete: the episodes a collection holds are those of its files, and nothing else keeps a count that could
  disagree with them.
- ``.NAME.partial/assembling/``: the Minari dataset built from the episode files once all of them are there,
  renamed to ``assembled/`` when complete. A kill while it is built loses nothing: it is built again from the files.
- ``.NAME.publishing/``: the partial folder renamed once ``assembled/`` is complete, the point from which the new
  dataset wins; then ``NAME`` (if there is one) is renamed to ``.NAME.old``, ``assembled/`` to ``NAME``, and the
  other two are removed. The next start completes a swap a kill cut short (:meth:`DatasetFiles.recover`).
- ``.NAME.lock``: held (``flock``) by the process writing ``NAME``; the kernel lets go of it when the process ends.

``SB3_CQL_CRASH_AT=POINT`` kills the process (``SIGKILL``) at one of :data:`CRASH_POINTS`, for the tests that check
these claims with real kills at the moments that timing alone rarely hits.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import pickle
import re
import shlex
import shutil
import signal
from collections.abc import Iterator
from pathlib import Path

from minari import MinariDataset
from minari.data_collector import EpisodeBuffer
from minari.dataset.minari_dataset import parse_dataset_id
from minari.namespace import create_namespace, list_local_namespaces

from sb3_cql.data import ids
from sb3_cql.data.errors import DatasetError
from sb3_cql.files import replace_atomically, sync_folder, write_atomically

#: The environment variable that names the crash point to kill the process at.
CRASH_AT_ENV = "SB3_CQL_CRASH_AT"
#: Where :func:`crash_point` is called: inside an episode file's write, before its rename, after the assembly's first
#: episode, after the assembly, between a swap's two renames, and before the old dataset and partial folder go.
CRASH_POINTS = ("episodes-write", "episodes-written", "assemble", "assembled", "swap", "published")
#: Bytes written at a time into an episode file.
WRITE_BLOCK = 1 << 16
#: Errors of a full disk (or quota).
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)

_EPISODE_FILE = re.compile(r"(\d{6,})-(\d{6,})\.pkl")


def crash_point(name: str) -> None:
    """Kill this process at once (``SIGKILL``: no cleanup) if :data:`CRASH_AT_ENV` names ``name``."""
    if os.environ.get(CRASH_AT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)


def _write_episode_file(path: Path, data: bytes) -> None:
    """Write an episode file atomically, :data:`WRITE_BLOCK` bytes at a time, with its two crash points."""

    def write(temporary: Path) -> None:
        with open(temporary, "xb") as file:
            for start in range(0, max(len(data), 1), WRITE_BLOCK):
                file.write(data[start : start + WRITE_BLOCK])
                if start == 0:
                    crash_point("episodes-write")

    replace_atomically(path, write, before_rename=lambda: crash_point("episodes-written"))


class DatasetFiles:
    """The folders and files of dataset ``dataset_id`` (a Minari id) and of its collection in progress."""

    def __init__(self, dataset_id: str) -> None:
        self.dataset_id = dataset_id
        self.final = ids.dataset_path(dataset_id)
        self.partial = ids.partial_path(dataset_id)
        self.publishing = self.final.with_name(f".{self.final.name}.publishing")
        self.old = self.final.with_name(f".{self.final.name}.old")
        self.lock_file = self.final.with_name(f".{self.final.name}.lock")
        self.spec_file = self.partial / ids.SPEC_FILE
        self.episodes = self.partial / "episodes"
        self.assembling = self.partial / "assembling"
        self.assembled = self.partial / "assembled"
        #: The folder of the collection's Minari storage before episode files (it is read once, into them).
        self.storage_before_episode_files = self.partial / "data"

    # The lock ----------------------------------------------------------------------------------------------------

    @contextlib.contextmanager
    def locked(self, wait: bool = False) -> Iterator[None]:
        """Hold the dataset's lock while the block runs; another holder (unless ``wait``) or a folder that cannot be
        written is one :class:`DatasetError`."""
        try:
            self.final.parent.mkdir(parents=True, exist_ok=True)
            descriptor = os.open(self.lock_file, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise DatasetError(f"cannot write dataset {self.dataset_id} in {self.final.parent}: {_reason(error)}") from None
        try:
            import fcntl

            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            except BlockingIOError:
                raise DatasetError(
                    f"dataset {self.dataset_id} is being written by another process (pid {self.holder()}, which holds "
                    f"{self.lock_file}): wait for it to end, or stop it and run the command again"
                ) from None
            os.ftruncate(descriptor, 0)
            os.pwrite(descriptor, str(os.getpid()).encode(), 0)
            yield
        finally:
            os.close(descriptor)  # lets go of the lock

    def holder(self) -> str:
        """The pid written in the lock file by the process that holds (or last held) the lock."""
        try:
            return self.lock_file.read_text().strip() or "?"
        except OSError:
            return "?"

    def is_locked(self) -> bool:
        """Whether another process holds the dataset's lock now."""
        try:
            import fcntl

            descriptor = os.open(self.lock_file, os.O_RDONLY)
        except (OSError, ImportError):
            return False
        try:
            fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        finally:
            os.close(descriptor)
        return False

    def check_writable(self) -> None:
        """One :class:`DatasetError` if the partial folder is there and cannot be written."""
        if not self.partial.is_dir():
            return
        probe = self.partial / f".write-probe-{os.getpid()}"
        try:
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as error:
            raise DatasetError(
                f"cannot write in {self.partial}, where the collection of {self.dataset_id} is kept: {_reason(error)}"
            ) from None

    # Swaps ---------------------------------------------------------------------------------------------------------

    def recover(self) -> None:
        """Complete a publication (:meth:`publish`) that a kill cut short. Call it holding the lock."""
        if self.publishing.exists():
            assembled = self.publishing / self.assembled.name
            if assembled.is_dir():
                if self.final.exists() and not self.old.exists():
                    os.replace(self.final, self.old)
                if not self.final.exists():
                    os.replace(assembled, self.final)
            shutil.rmtree(self.old, ignore_errors=True)
            shutil.rmtree(self.publishing, ignore_errors=True)
        elif self.old.exists():  # the swap was done, and only the removal of the old copy was cut short
            if self.final.exists():
                shutil.rmtree(self.old, ignore_errors=True)
            else:
                os.replace(self.old, self.final)

    def publish(self) -> Path:
        """Put ``assembled/`` in place of the dataset's folder by renames, remove the partial folder, return the
        dataset's folder."""
        os.replace(self.partial, self.publishing)  # from here on, the new dataset wins
        if self.final.exists():
            os.replace(self.final, self.old)
            crash_point("swap")
        os.replace(self.publishing / self.assembled.name, self.final)
        sync_folder(self.final.parent)
        crash_point("published")
        shutil.rmtree(self.old, ignore_errors=True)
        shutil.rmtree(self.publishing, ignore_errors=True)
        return self.final

    # The collection in progress ------------------------------------------------------------------------------------

    def spec(self) -> str | None:
        """The spec (JSON) of the collection in progress, or ``None`` if there is none."""
        try:
            return self.spec_file.read_text()
        except FileNotFoundError:
            return None
        except (OSError, UnicodeDecodeError) as error:
            raise DatasetError(f"cannot read {self.spec_file} of a collection of {self.dataset_id}: {error}") from None

    def start(self, spec: str) -> None:
        """Begin a collection of ``spec`` (JSON) in an empty partial folder."""
        self.episodes.mkdir(parents=True, exist_ok=True)
        write_atomically(self.spec_file, spec)

    def holds_anything(self) -> bool:
        return self.partial.is_dir() and any(self.partial.iterdir())

    def holds_no_episodes(self) -> bool:
        """Whether the partial folder is a collection that kept no episode, which another may replace losing nothing."""
        if not self.partial.is_dir() or {path.name for path in self.partial.iterdir()} - {ids.SPEC_FILE, self.episodes.name}:
            return False
        return not self.episodes.is_dir() or not any(self.episodes.iterdir())

    def episode_files(self) -> list[tuple[range, Path]]:
        """The episode files of the collection, in episode order: ``(indices, path)``."""
        if not self.episodes.is_dir():
            return []
        found = []
        for path in self.episodes.iterdir():
            match = _EPISODE_FILE.fullmatch(path.name)
            if match:
                found.append((range(int(match[1]), int(match[2]) + 1), path))
        return sorted(found, key=lambda item: item[0].start)

    def episodes_held(self) -> int:
        """How many episodes the collection's files hold (by their names: complete files only)."""
        return sum(len(indices) for indices, _ in self.episode_files())

    def write_episodes(self, episodes: list[EpisodeBuffer]) -> None:
        """Write consecutive ``episodes`` as one file, atomically; a full disk is one :class:`DatasetError`."""
        first, last = episodes[0].id, episodes[-1].id
        path = self.episodes / f"{first:06d}-{last:06d}.pkl"
        try:
            _write_episode_file(path, pickle.dumps(episodes, protocol=pickle.HIGHEST_PROTOCOL))
        except OSError as error:
            if error.errno not in NO_SPACE:
                raise
            raise DatasetError(
                f"no space left in {self.partial.parent} for episodes {first}-{last} of {self.dataset_id}: the "
                f"{self.episodes_held()} episodes written before are kept in {self.partial}; free some space and run "
                "the same command to resume"
            ) from None

    @staticmethod
    def read_episodes(path: Path) -> list[EpisodeBuffer]:
        """The episodes of one file of :meth:`episode_files`."""
        with open(path, "rb") as file:
            return pickle.load(file)

    def read_storage_before_episode_files(self) -> list[EpisodeBuffer]:
        """The episodes of the collection's Minari storage of before episode files whose HDF5 groups read whole, from
        the first on (its ``metadata.json``'s count could be behind the file)."""
        import h5py
        import numpy as np

        episodes: list[EpisodeBuffer] = []
        data_file = self.storage_before_episode_files / "main_data.hdf5"
        try:
            file = h5py.File(data_file, "r")
        except OSError:
            return episodes
        with file:
            while f"episode_{len(episodes)}" in file:
                try:
                    group = file[f"episode_{len(episodes)}"]
                    arrays = {key: np.asarray(group[key]) for key in
                              ("observations", "actions", "rewards", "terminations", "truncations")}  # fmt: skip
                    infos = {key: np.asarray(value) for key, value in group["infos"].items()} if "infos" in group else {}
                    episodes.append(EpisodeBuffer(id=len(episodes), seed=int(group.attrs["seed"]), **arrays,
                                                  infos=infos or None))  # fmt: skip
                except (KeyError, OSError, ValueError, RuntimeError):  # a group cut short by a kill
                    break
        return episodes


def partial_summary(files: DatasetFiles) -> tuple[dict, int] | None:
    """``(spec fields, episodes held)`` of the collection in progress of ``files``, or ``None`` (none readable)."""
    try:
        spec = files.spec()
        return (json.loads(spec), files.episodes_held()) if spec is not None else None
    except (DatasetError, ValueError):
        return None


def _reason(error: OSError) -> str:
    return error.strerror or str(error)


def load_dataset(dataset_id: str) -> MinariDataset:
    """Open the Minari dataset ``dataset_id`` (completing a replacement a kill cut short, unless a collection of it
    runs), with a :class:`DatasetError` naming it and how to make it if it is missing, partial, damaged or unreadable."""
    files = DatasetFiles(dataset_id)
    if (files.publishing.exists() or files.old.exists()) and not files.is_locked():
        with contextlib.suppress(DatasetError, OSError), files.locked():
            files.recover()
    path = ids.dataset_path(dataset_id)
    if not ids.dataset_exists(dataset_id):
        if path.exists():
            raise DatasetError(damaged_dataset(dataset_id))
        partial = _partial_collection(files)
        if partial is not None:
            raise DatasetError(partial)
        raise DatasetError(
            f"dataset {dataset_id} not found at {path} (MINARI_DATASETS_PATH or ~/.minari/datasets); "
            f"collect it with: python -m sb3_cql.data collect --dataset-id {shlex.quote(dataset_id)} ..."
        )
    try:
        dataset = MinariDataset(path / "data")
        empty = dataset.total_episodes == 0
        if not empty:
            list(dataset.storage.get_episode_metadata([0, dataset.total_episodes - 1]))  # opens the data file
    except Exception as error:
        raise DatasetError(f"dataset {dataset_id} at {path} is truncated or corrupt: {error}") from error
    if empty:
        raise DatasetError(f"dataset {dataset_id} at {path} holds no episodes: nothing to train on; collect it again "
                           "(python -m sb3_cql.data collect ... --overwrite)")  # fmt: skip
    return dataset


def damaged_dataset(dataset_id: str) -> str:
    """What to say of a dataset folder without its ``data/metadata.json`` (Minari writes it last)."""
    path = ids.dataset_path(dataset_id)
    fields = ids.standard_collection_fields(dataset_id)
    command = ids.collect_command(fields, dataset_id) if fields is not None else None
    again = command or f"python -m sb3_cql.data collect --dataset-id {shlex.quote(dataset_id)} ..."
    return (
        f"dataset {dataset_id} at {path} is damaged: it has no data/metadata.json and cannot be read; replace it with: "
        f"{again} --overwrite"
    )


def _partial_collection(files: DatasetFiles) -> str | None:
    """What to say of an interrupted collection of ``files``'s dataset, or ``None`` if there is none."""
    summary = partial_summary(files)
    if summary is None:
        return None
    spec, collected = summary
    command = ids.collect_command(spec, files.dataset_id)
    resume = f"resume it with: {command}" if command else "the same collection (collect_dataset) resumes it"
    if files.storage_before_episode_files.is_dir():  # written before episode files: its metadata has a count
        with contextlib.suppress(OSError, ValueError, KeyError):
            metadata = json.loads((files.storage_before_episode_files / "metadata.json").read_text())
            collected += int(metadata["total_episodes"])
    return (
        f"dataset {files.dataset_id} is partial: its collection was interrupted after {collected} of "
        f"{spec['n_episodes']} episodes (kept in {files.partial}); {resume}"
    )


def other_collection(files: DatasetFiles, held_spec: str | None) -> str:
    """What to say of a partial collection of ``files``'s id that is not the one asked for."""
    summary = partial_summary(files)
    replace = "pass --overwrite (overwrite=True) to replace it"
    if summary is None:
        what = f"{files.partial} holds files of a collection of {files.dataset_id} whose spec cannot be read"
        if held_spec is None:
            what = f"{files.partial} holds files that are not a collection of {files.dataset_id}"
        return f"{what}: {replace}"
    fields, held = summary
    command = ids.collect_command(fields, files.dataset_id)
    resume = f"resume it with: {command}" if command else "the collection of that spec resumes it"
    return (
        f"a partial collection of {files.dataset_id} is in {files.partial}: {held} of {fields['n_episodes']} episodes of "
        f"another collection ({fields['policy']} policy, seed {fields['seed']}, noise {fields['noise']}, env_kwargs "
        f"{fields['env_kwargs']}); {resume}, or {replace}"
    )


def prepare_folder(dataset_id: str, overwrite: bool) -> Path:
    """The folder of ``dataset_id``, its Minari namespace created; a dataset there is a ``FileExistsError`` unless
    ``overwrite``, a damaged one a :class:`DatasetError`."""
    final = ids.dataset_path(dataset_id)
    if final.exists() and not overwrite:
        if not ids.dataset_exists(dataset_id):
            raise DatasetError(damaged_dataset(dataset_id))
        raise FileExistsError(f"dataset {dataset_id} already exists at {final}: pass overwrite=True (--overwrite)")
    namespace = parse_dataset_id(dataset_id)[0]
    if namespace is not None and namespace not in list_local_namespaces():
        create_namespace(namespace, description="Panda grasping datasets written by sb3-cql")
    return final
