"""Collect behaviour-policy rollouts into Minari datasets, in parallel, resumably and atomically.

Episode ``i`` of a collection is reset with ``seed + i`` and draws its noise from a generator seeded with
``(seed, i)``, so a dataset does not depend on the number of workers and an interrupted collection resumes
exactly where it stopped.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import shutil
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import gymnasium as gym
import minari
import numpy as np
from minari import MinariDataset
from minari.data_collector import EpisodeBuffer
from minari.dataset.minari_dataset import parse_dataset_id
from minari.dataset.minari_storage import MinariStorage
from minari.namespace import create_namespace, list_local_namespaces
from minari.utils import validate_datasets_to_combine
from tqdm import tqdm

import envs
from sb3_cql.data import ids
from sb3_cql.data.ids import DEFAULT_NOISE, NOISY_POLICIES, POLICIES
from sb3_cql.data.replay import load_dataset

#: Episodes written to disk at a time: the most an interruption can lose.
WRITE_EVERY = 50
#: Name of the file describing a collection in progress (to resume only the same collection).
SPEC_FILE = "collection.json"

Policy = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, np.ndarray | None]]


@dataclasses.dataclass(frozen=True)
class CollectionSpec:
    """What a dataset is made of; two collections with equal specs write identical data.

    :param env_id: gymnasium id of the task.
    :param policy: ``"pid"``, ``"noisy"`` (PD with Gaussian noise on the executed arm targets), ``"pid-regrasp"``
        and ``"noisy-regrasp"`` (the same with the PD controller that grasps a lost object again), ``"random"``
        (uniform actions), or the path of a saved SB3 model.
    :param n_episodes: number of episodes.
    :param seed: episode ``i`` is reset with ``seed + i``.
    :param noise: standard deviation (rad) of the noise on the executed arm joint targets; ``None`` means
        0.03 for the noisy policies and 0 otherwise.
    :param env_kwargs: keywords for ``gymnasium.make`` (``action_mode``, physics).
    :param algo: the SB3 algorithm of a model policy, a key of RL-Zoo3's ``ALGOS`` (``"sac"``, ``"cql"``...).
    """

    env_id: str = "Panda-v0"
    policy: str = "pid"
    n_episodes: int = 10_000
    seed: int = 0
    noise: float | None = None
    env_kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    algo: str | None = None

    def __post_init__(self) -> None:
        if self.policy not in POLICIES and not Path(self.policy).is_file():
            raise ValueError(f"policy must be one of {POLICIES} or the path of a saved SB3 model, got {self.policy!r}")
        if self.policy not in POLICIES and self.algo is None:
            raise ValueError(f"a model policy ({self.policy}) needs algo, e.g. algo='sac'")
        if self.n_episodes < 1:
            raise ValueError(f"n_episodes must be >= 1, got {self.n_episodes}")
        if self.noise is None:
            object.__setattr__(self, "noise", DEFAULT_NOISE if self.policy in NOISY_POLICIES else 0.0)
        if self.noise < 0:
            raise ValueError(f"noise must be >= 0, got {self.noise}")

    @property
    def controller(self) -> str | None:
        """The name of the PD controller behind the policy (a key of ``envs.CONTROLLERS``), if it is one."""
        name = NOISY_POLICIES.get(self.policy, self.policy)
        return name if name in envs.CONTROLLERS else None

    @property
    def action_mode(self) -> str:
        return self.env_kwargs.get("action_mode", "absolute")

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)


def make_policy(spec: CollectionSpec, env: gym.Env) -> Policy:
    """The behaviour policy of ``spec`` for ``env``: a function ``(observation, rng) -> (executed action,
    clean action or None)``. The clean action is the policy's own before noise, kept for imitation."""
    action_space = env.action_space
    if spec.policy == "random":
        return lambda observation, rng: (rng.uniform(action_space.low, action_space.high).astype(np.float32), None)
    if spec.controller is not None:
        predict = envs.PDController.for_env(env, **envs.CONTROLLERS[spec.controller]).predict
    else:
        from rl_zoo3.utils import ALGOS

        model = ALGOS[spec.algo].load(spec.policy, device="cpu")
        predict = model.predict
    if spec.noise == 0:
        return lambda observation, rng: (predict(observation, deterministic=True)[0], None)
    unwrapped = env.unwrapped
    # Noise is specified on the arm's joint targets (rad); a delta action moves a target by arm_max_delta.
    scale = np.zeros(action_space.shape, dtype=np.float64)
    n_arm = len(envs.robot.ARM_JOINTS)
    scale[:n_arm] = spec.noise / (unwrapped.config.arm_max_delta if unwrapped.action_mode == "delta" else 1.0)

    def noisy_policy(observation: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        clean = predict(observation, deterministic=True)[0]
        executed = np.clip(clean + scale * rng.standard_normal(scale.shape), action_space.low, action_space.high)
        return executed.astype(np.float32), clean

    return noisy_policy


_worker: dict[str, Any] = {}


def _init_worker(spec: CollectionSpec) -> None:
    env = gym.make(spec.env_id, **spec.env_kwargs)
    _worker.update(spec=spec, env=env, policy=make_policy(spec, env))


def _run_episode(index: int) -> EpisodeBuffer:
    """Roll out episode ``index`` of the worker's collection."""
    spec, env, policy = _worker["spec"], _worker["env"], _worker["policy"]
    rng = np.random.default_rng((spec.seed, index))
    observation, _ = env.reset(seed=spec.seed + index)
    observations, actions, clean_actions, rewards, terminations, truncations = [observation], [], [], [], [], []
    done = False
    while not done:
        action, clean = policy(observation, rng)
        observation, reward, terminated, truncated, _ = env.step(action)
        observations.append(observation)
        actions.append(action)
        clean_actions.append(clean)
        rewards.append(reward)
        terminations.append(terminated)
        truncations.append(truncated)
        done = terminated or truncated
    infos = None
    if clean_actions[0] is not None:
        # Minari aligns infos with observations: the last one gets the clean action at the final observation.
        clean_actions.append(policy(observation, rng)[1])
        infos = {"clean_action": np.asarray(clean_actions, dtype=np.float32)}
    return EpisodeBuffer(
        id=index,
        seed=spec.seed + index,
        observations=np.asarray(observations, dtype=np.float32),
        actions=np.asarray(actions, dtype=np.float32),
        rewards=np.asarray(rewards, dtype=np.float64),
        terminations=np.asarray(terminations, dtype=bool),
        truncations=np.asarray(truncations, dtype=bool),
        infos=infos,
    )


def _episodes(spec: CollectionSpec, start: int, workers: int) -> Iterator[EpisodeBuffer]:
    """Episodes ``start .. n_episodes - 1`` in order, from ``workers`` processes (in this one if 1)."""
    indices = range(start, spec.n_episodes)
    if workers == 1:
        _init_worker(spec)
        try:
            yield from map(_run_episode, indices)
        finally:
            _worker["env"].close()
            _worker.clear()
        return
    # spawn, not fork: a parent holding torch threads or a PyBullet client must not be copied. An executor, not
    # a Pool: a killed worker raises BrokenProcessPool instead of hanging the collection.
    executor = ProcessPoolExecutor(workers, multiprocessing.get_context("spawn"), _init_worker, (spec,))
    try:
        yield from executor.map(_run_episode, indices, chunksize=4)
    except BrokenProcessPool as error:
        raise RuntimeError(
            f"a collection worker died (killed, or out of memory); the episodes written so far are kept and "
            f"running the same collection again resumes it: {error}"
        ) from error
    finally:
        executor.shutdown(wait=False, cancel_futures=True)


def _open_partial(partial: Path, spec: CollectionSpec, env: gym.Env) -> tuple[MinariStorage, list[bool]]:
    """The storage of an interrupted collection of the same spec and the successes of its episodes, or a new
    storage. Anything else in ``partial`` (another spec, an unreadable file) is removed, never trusted."""
    spec_file = partial / SPEC_FILE
    if spec_file.exists() and spec_file.read_text() == spec.to_json():
        try:
            storage = MinariStorage.read(partial / "data")
            episodes = storage.get_episodes(range(storage.total_episodes))
            return storage, [bool(episode["rewards"][-1] > 0) for episode in episodes]
        except Exception:
            pass
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    storage = MinariStorage.new(partial / "data", env_spec=env.spec, data_format="hdf5")
    spec_file.write_text(spec.to_json())
    return storage, []


def collect_dataset(
    spec: CollectionSpec,
    dataset_id: str | None = None,
    workers: int = 1,
    overwrite: bool = False,
    progress_bar: bool = True,
) -> MinariDataset:
    """Collect ``spec.n_episodes`` episodes into the Minari dataset ``dataset_id`` and return it.

    The data go to a hidden ``.partial`` folder beside the dataset, ``WRITE_EVERY`` episodes at a time, and are
    renamed to the dataset's folder only when complete: an interrupted collection leaves no dataset under its
    id, and running the same collection again resumes it. Actions are the executed ones; with noise, the
    policy's clean actions are in the episodes' ``infos["clean_action"]``.

    :param spec: what to collect.
    :param dataset_id: the Minari id; by default ``sb3cql/<env>/<policy>[-delta]-v0``.
    :param workers: worker processes; the data do not depend on it.
    :param overwrite: replace an existing dataset of that id (otherwise ``FileExistsError``).
    :param progress_bar: show episodes, transitions/s and the success rate so far.
    """
    policy_name = spec.policy if spec.policy in POLICIES else Path(spec.policy).stem
    dataset_id = dataset_id or ids.dataset_id(spec.env_id, policy_name, spec.action_mode)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    final = _prepare(dataset_id, overwrite)

    env = gym.make(spec.env_id, **spec.env_kwargs)
    partial = final.with_name(f".{final.name}.partial")
    storage, successes = _open_partial(partial, spec, env)
    start = storage.total_episodes
    steps, pending, begin = 0, [], time.perf_counter()
    with tqdm(total=spec.n_episodes, initial=start, desc=dataset_id, unit="ep", disable=not progress_bar) as bar:
        for episode in _episodes(spec, start, workers):
            pending.append(episode)
            successes.append(bool(episode.rewards[-1] > 0))
            steps += len(episode.rewards)
            bar.update()
            rate = steps / (time.perf_counter() - begin)
            bar.set_postfix(transitions_per_s=f"{rate:.0f}", success_rate=f"{np.mean(successes):.3f}")
            if len(pending) == WRITE_EVERY:
                storage.update_episodes(pending)
                pending = []
        storage.update_episodes(pending)

    storage.update_metadata(_metadata(dataset_id, spec, successes, env))
    env.close()
    (partial / SPEC_FILE).unlink()
    return _publish(partial, final)


def ensure_dataset(
    dataset_id: str, n_episodes: int | None = None, workers: int | None = None, progress_bar: bool = True
) -> MinariDataset:
    """The dataset ``dataset_id``, collected first if it is missing and its id is one of this package's standard
    ones (``sb3cql/<task>/<pid|noisy|random>[-delta]-v0``, collected with :class:`CollectionSpec`'s defaults:
    10,000 episodes from seed 0). Any other missing id raises :class:`~sb3_cql.data.DatasetError`. An interrupted
    collection resumes.

    :param dataset_id: the Minari id.
    :param n_episodes: episodes of a collection; ``None`` for :class:`CollectionSpec`'s default.
    :param workers: collection processes; by default one per CPU.
    :param progress_bar: show the collection's progress.
    """
    parsed = ids.parse_dataset_id(dataset_id)
    if ids.dataset_exists(dataset_id) or parsed is None or parsed[3] != 0 or parsed[0] not in envs.ENV_IDS:
        return load_dataset(dataset_id)  # an error naming the id if it is missing
    env_id, policy, action_mode, _ = parsed
    env_kwargs = {"action_mode": action_mode} if action_mode != "absolute" else {}
    spec = CollectionSpec(env_id, policy, env_kwargs=env_kwargs, **({} if n_episodes is None else {"n_episodes": n_episodes}))
    print(f"Dataset {dataset_id} not found: collecting it ({spec.n_episodes} episodes), once.")
    return collect_dataset(spec, dataset_id, workers=workers or os.cpu_count() or 1, progress_bar=progress_bar)


def mix_datasets(source_ids: list[str], dataset_id: str, overwrite: bool = False) -> MinariDataset:
    """Combine the datasets ``source_ids`` (same env and spaces) into a new dataset ``dataset_id``, written
    atomically like :func:`collect_dataset`; its metadata lists them under ``combined_datasets``."""
    from sb3_cql.data.replay import load_dataset

    final = _prepare(dataset_id, overwrite)
    sources = [load_dataset(source) for source in source_ids]
    env_spec = validate_datasets_to_combine(sources)
    partial = final.with_name(f".{final.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    storage = MinariStorage.new(partial / "data", env_spec=env_spec, data_format="hdf5")
    for source in sources:
        storage.update_from_storage(source.storage)
    successes = [bool(e["rewards"][-1] > 0) for e in storage.get_episodes(range(storage.total_episodes))]
    storage.update_metadata(
        {
            "dataset_id": dataset_id,
            "minari_version": minari.__version__,
            "combined_datasets": list(source_ids),
            "description": f"the datasets {', '.join(source_ids)} combined",
            "success_rate": float(np.mean(successes)),
            **{key: sources[0].storage.metadata[key] for key in ("env_id", "env_kwargs", "ref_min_score", "ref_max_score")},
        }
    )
    return _publish(partial, final)


def _prepare(dataset_id: str, overwrite: bool) -> Path:
    """The folder of ``dataset_id``, after checking it may be written and creating its Minari namespace."""
    final = ids.dataset_path(dataset_id)
    if final.exists() and not overwrite:
        raise FileExistsError(f"dataset {dataset_id} already exists at {final}: pass overwrite=True (--overwrite)")
    namespace = parse_dataset_id(dataset_id)[0]
    if namespace is not None and namespace not in list_local_namespaces():
        create_namespace(namespace, description="Panda grasping datasets written by sb3-cql")
    return final


def _publish(partial: Path, final: Path) -> MinariDataset:
    """Move a complete dataset from ``partial`` to ``final`` (replacing it) by renames, so that ``final`` never
    holds half a dataset."""
    if final.exists():
        old = final.with_name(f".{final.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
        os.replace(partial, final)
        shutil.rmtree(old)
    else:
        os.replace(partial, final)
    return MinariDataset(final / "data")


def _metadata(dataset_id: str, spec: CollectionSpec, successes: list[bool], env: gym.Env) -> dict[str, Any]:
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
    }
    if spec.controller is not None:
        controller = envs.PDController.for_env(env, **envs.CONTROLLERS[spec.controller])
        try:
            metadata["controller"] = json.dumps(controller.parameters())
        finally:
            controller.close()
    return metadata
