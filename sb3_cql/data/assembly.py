"""Minari datasets assembled in the store's ``assembling/`` folder from a collection's episode files (:func:`assemble`)
or other datasets (:func:`mix_datasets`)."""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import minari
import numpy as np
from minari import MinariDataset
from minari.dataset.minari_storage import MinariStorage
from minari.utils import validate_datasets_to_combine

import envs
from sb3_cql.data.digest import update_digest
from sb3_cql.data.errors import DatasetError
from sb3_cql.data.estimates import BYTES_PER_EPISODE, check_space
from sb3_cql.data.ids import POLICIES
from sb3_cql.data.rollouts import CollectionSpec
from sb3_cql.data.store import DatasetFiles, crash_point, load_dataset, other_collection, prepare_folder
from sb3_cql.processes import interrupts_deferred


def assemble(files: DatasetFiles, env: gym.Env, metadata: Callable[[list[bool]], dict[str, Any]]) -> None:
    """Build the Minari dataset from the collection's episode files in ``assembling/``, with ``metadata(successes)``,
    and rename it to ``assembled/`` once complete (built again from the files after a kill)."""
    shutil.rmtree(files.assembling, ignore_errors=True)
    if files.assembled.is_dir():  # complete already: a kill came after it was built
        return
    episode_files = files.episode_files()
    data_bytes = sum(path.stat().st_size for _, path in episode_files)
    check_space(files, data_bytes + sum(map(len, (i for i, _ in episode_files))) * BYTES_PER_EPISODE, "its assembly")
    files.assembling.mkdir()
    # With the spaces given, Minari makes no env of its own (whose PyBullet __del__ could drop a Ctrl-C).
    storage = MinariStorage.new(files.assembling / "data", env.observation_space, env.action_space, env.spec,
                                data_format="hdf5")  # fmt: skip
    successes, digest = [], hashlib.sha256()
    try:
        for _, path in episode_files:
            episodes = files.read_episodes(path)
            storage.update_episodes(episodes)
            successes += [bool(episode.rewards[-1] > 0) for episode in episodes]
            for episode in episodes:
                update_digest(digest, episode)
            crash_point("assemble")
        storage.update_metadata({**metadata(successes), "arrays_sha256": digest.hexdigest()})
    except OSError as error:
        shutil.rmtree(files.assembling, ignore_errors=True)
        raise DatasetError(
            f"cannot write the dataset {files.dataset_id} in {files.assembling}: {' '.join(str(error).split())}; "
            f"its {files.episodes_held()} episodes are kept in {files.episodes}, and the same command assembles it"
        ) from None
    os.replace(files.assembling, files.assembled)
    crash_point("assembled")


#: The packages whose versions can change what a collection writes, recorded in its metadata (``packages``).
COLLECTION_PACKAGES = ("sb3-cql", "numpy", "gymnasium", "pybullet", "torch", "stable-baselines3", "minari")


def package_versions() -> str:
    """The installed versions of :data:`COLLECTION_PACKAGES`, as JSON (``null`` for one not installed)."""
    versions = {}
    for name in COLLECTION_PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return json.dumps(versions)


def collection_metadata(dataset_id: str, spec: CollectionSpec, successes: list[bool], env: gym.Env) -> dict[str, Any]:
    unwrapped = env.unwrapped
    description = (
        f"{spec.n_episodes} episodes of {spec.env_id} ({spec.action_mode} actions) collected by the {spec.policy} "
        f"policy" + (f" with N(0, {spec.noise}^2) rad noise on the executed arm targets" if spec.noise else "")
    )
    metadata = {
        "dataset_id": dataset_id,
        "minari_version": minari.__version__,
        "algorithm_name": spec.policy if spec.policy in POLICIES else f"{spec.algo}:{Path(spec.policy).name}",
        "author": {"sb3-cql"},
        "code_permalink": "https://github.com/sb3-cql/sb3-cql",
        "description": description,
        # Sparse success reward: an episode's return is 0 or 1.
        "ref_min_score": 0.0,
        "ref_max_score": 1.0,
        "env_id": spec.env_id,
        "env_kwargs": json.dumps({**unwrapped.config.to_kwargs(), "action_mode": unwrapped.action_mode}),
        "collection": spec.to_json(),
        "success_rate": float(np.mean(successes)),
        "packages": package_versions(),
    }
    if spec.controller is not None:
        controller = envs.PDController.for_env(env, **envs.CONTROLLERS[spec.controller])
        try:
            parameters = controller.parameters()
        finally:
            controller.close()
        if controller.yaw == "random":
            parameters["yaw_episode_seed"] = f"episode i: PDController.seed(({spec.seed}, i))"
        metadata["controller"] = json.dumps(parameters)
    return metadata


def _made_in(dataset: MinariDataset) -> str:
    """The env id and action mode a dataset was collected in, from its metadata."""
    metadata = dataset.storage.metadata
    try:
        action_mode = json.loads(metadata.get("env_kwargs") or "{}").get("action_mode", "absolute")
    except (TypeError, ValueError):
        action_mode = "?"
    return f"{metadata.get('env_id', '?')}, action_mode {action_mode!r}"


#: The metadata a combined dataset takes from its first source.
METADATA_OF_THE_FIRST = ("env_id", "env_kwargs", "ref_min_score", "ref_max_score")


def mix_datasets(source_ids: list[str], dataset_id: str, overwrite: bool = False) -> MinariDataset:
    """Combine the datasets ``source_ids`` (same env and spaces) into a new dataset ``dataset_id``, written
    atomically like :func:`collect_dataset`; its metadata lists them under ``combined_datasets``."""
    files = DatasetFiles(dataset_id)
    with files.locked():
        files.recover()
        prepare_folder(dataset_id, overwrite)
        sources = [load_dataset(source) for source in source_ids]
        try:
            env_spec = validate_datasets_to_combine(sources)
        except ValueError:  # Minari's message names env specs, not what differs
            made = "; ".join(f"{source_id}: {_made_in(source)}" for source_id, source in zip(source_ids, sources, strict=True))
            raise DatasetError(f"cannot mix datasets of different envs or action modes ({made}): mix datasets of one env "
                               "and action mode") from None  # fmt: skip
        if files.holds_anything():
            if not overwrite:
                raise DatasetError(other_collection(files, files.spec()))
            shutil.rmtree(files.partial)
        files.assembling.mkdir(parents=True)
        storage = MinariStorage.new(files.assembling / "data", env_spec=env_spec, data_format="hdf5")
        for source in sources:
            storage.update_from_storage(source.storage)
        successes, digest = [], hashlib.sha256()
        for episode in storage.get_episodes(range(storage.total_episodes)):
            successes.append(bool(episode["rewards"][-1] > 0))
            update_digest(digest, SimpleNamespace(**episode))
        storage.update_metadata(
            {
                "dataset_id": dataset_id,
                "minari_version": minari.__version__,
                "combined_datasets": list(source_ids),
                "description": f"the datasets {', '.join(source_ids)} combined",
                "success_rate": float(np.mean(successes)),
                "arrays_sha256": digest.hexdigest(),
                "packages": package_versions(),
                **{key: sources[0].storage.metadata[key] for key in METADATA_OF_THE_FIRST},
            }
        )
        os.replace(files.assembling, files.assembled)
        with interrupts_deferred(sigterm_as_interrupt=True):
            return MinariDataset(files.publish() / "data")
