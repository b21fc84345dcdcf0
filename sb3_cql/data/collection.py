"""Collect behaviour-policy rollouts into Minari datasets, in parallel, resumably and atomically.

Episode ``i`` of a collection is reset with ``seed + i``, draws its noise from a generator seeded with ``(seed, i)``
and seeds a PD controller's random yaws with ``(seed, i)`` too (``PDController.seed``: a stream of their own), so a
dataset does not depend on the number of workers and an interrupted collection resumes exactly where it stopped.

Before it starts, a collection prints (on stderr) what it will do: the episodes, the workers, and about how long
and how much disk it takes, from the measurements below; a resumed one says how many episodes it already has. On
Ctrl-C or SIGTERM, the episodes finished are written, one line says how many are kept, and ``KeyboardInterrupt`` goes
on to the caller; the workers ignore both, the parent stops them, and they die with it if it is killed. The files
a collection writes, and why a kill at any instant loses nothing kept, are :mod:`sb3_cql.data.partial`'s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import multiprocessing
import os
import shutil
import signal
import sys
import threading
import time
from collections import deque
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
from envs.pd_controller import REFERENCE_CONTROLLERS
from sb3_cql.data import ids
from sb3_cql.data.ids import DEFAULT_NOISE, NOISY_POLICIES, POLICIES
from sb3_cql.data.partial import DatasetFiles, crash_point, partial_summary
from sb3_cql.data.replay import DatasetError, damaged_dataset, load_dataset
from sb3_cql.interrupts import die_with_parent

#: Episodes written to disk at a time: the most a crash (a killed process, a power cut) can lose. Ctrl-C loses none
#: of the finished ones: they are written before the collection stops.
WRITE_EVERY = 50

# The estimates a collection prints before it starts, measured on this project's 2-core machine. "About" is meant:
# other jobs on the CPUs slow a collection down (beside them, the collections of 2026-12-01 below ran at 30 to 75% of
# the rate below).

#: Mean transitions of an episode by task and policy: the PD controllers finish most Panda-v0 episodes in ~178 steps,
#: the noisy ones run most of them to the 700-step limit. Means over ``python -m sb3_cql.data collect --env ENV
#: --policy POLICY --episodes N`` (2026-12-01) with N = 100 to 200 for Panda-v0's noisy policies and PD controller,
#: 15 to 60 for the others; the action mode changes them by ~3% (Panda-v0's noisy-regrasp: 585 delta, 570 absolute).
#: The random-yaw policies' are the means over both action modes of the first 10 episodes from seed 0 (``collect_dataset``
#: with ``n_episodes=10``, 2026-12-02): a handful, so rougher (the modes' means differ by 1 to 4%).
EPISODE_STEPS = {
    "Panda-v0": {"pid": 178, "pid-regrasp": 178, "noisy": 629, "noisy-regrasp": 580, "pid-regrasp-yaw": 182,
                 "noisy-regrasp-yaw": 614, "random": 700},
    "PandaForce-v0": {"pid": 700, "pid-regrasp": 674, "noisy": 652, "noisy-regrasp": 700, "pid-regrasp-yaw": 696,
                      "noisy-regrasp-yaw": 678, "random": 700},
    "PandaPerturbed-v0": {"pid": 258, "pid-regrasp": 258, "noisy": 680, "noisy-regrasp": 642, "pid-regrasp-yaw": 184,
                          "noisy-regrasp-yaw": 676, "random": 700},
}  # fmt: skip
#: Transitions/s of one worker running a PD controller (noisy or not): 1,255 in ``python benchmarks/collect_speed.py``
#: (2026-11-22; 2,598 with 2 workers). Uniform random actions skip the controller's inverse kinematics: 1.8 to 2.2
#: times faster in back-to-back collections (2026-12-01). A model policy's speed is not estimated.
TRANSITIONS_PER_S = {"controller": 1_250, "random": 2_500}
#: Seconds before a worker's first episode (interpreter, imports, env and controller): 1.7 to 2.1 s in ``python -c
#: "from sb3_cql.data import collection as c; c._init_worker(c.CollectionSpec())"`` (2026-12-01, on a busy machine).
WORKER_START_S = 2.0
#: Disk of a dataset: per episode (HDF5 groups and attributes) and per transition (29 float32 observations, 9 float32
#: actions, a float64 reward, two flags, and HDF5's chunks); policies with noise also keep the clean actions
#: (``infos["clean_action"]``). Fitted 2026-12-01 to the HDF5 files of the collections above: 192 B a transition for
#: 700-step episodes without noise, 245 B for 178-step ones, 239-241 B for the noisy policies' ~600-step episodes.
BYTES_PER_EPISODE = 12_500
BYTES_PER_TRANSITION = 175
CLEAN_ACTION_BYTES_PER_TRANSITION = 45


@dataclasses.dataclass(frozen=True)
class CollectionSpec:
    """What a dataset is made of; two collections with equal specs write identical data.

    :param env_id: gymnasium id of the task.
    :param policy: ``"pid"``, ``"noisy"`` (PD with Gaussian noise on the executed arm targets), ``"pid-regrasp"``
        and ``"noisy-regrasp"`` (the same with the PD controller that grasps a lost object again),
        ``"pid-regrasp-yaw"`` and ``"noisy-regrasp-yaw"`` (the same with the hand's yaw drawn at random at each grasp
        attempt, seeded with ``(seed, i)`` in episode ``i``), ``"random"`` (uniform actions), or the path of a saved
        SB3 model.
    :param n_episodes: number of episodes.
    :param seed: episode ``i`` is reset with ``seed + i`` (an integer >= 0).
    :param noise: standard deviation (rad) of the noise on the executed arm joint targets, a finite number >= 0; ``None`` means
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
        if self.policy in REFERENCE_CONTROLLERS:
            raise ValueError(f"{self.policy} is a reference controller (evaluated, never collected); the policies: {POLICIES}")
        if self.policy not in POLICIES and not Path(self.policy).is_file():
            raise ValueError(f"policy must be one of {POLICIES} or the path of a saved SB3 model, got {self.policy!r}")
        if self.policy not in POLICIES and self.algo is None:
            raise ValueError(f"a model policy ({self.policy}) needs algo, e.g. algo='sac'")
        for name, lowest in (("n_episodes", 1), ("seed", 0)):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < lowest:
                raise ValueError(f"{name} must be an integer >= {lowest}, got {value!r}")
        if self.noise is None:
            object.__setattr__(self, "noise", DEFAULT_NOISE if self.policy in NOISY_POLICIES else 0.0)
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float)) or not 0 <= self.noise < float("inf"):
            raise ValueError(f"noise must be a finite number >= 0 (std in rad), got {self.noise!r}")

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


class BehaviourPolicy:
    """The behaviour policy of a collection in one env: :meth:`start` before each episode, then one call a step,
    ``policy(observation, rng) -> (executed action, clean action or None)``, ``rng`` the episode's noise generator.
    The clean action is the policy's own before noise, kept for imitation. A stateful policy's state (the attempt yaws
    of a PD controller) goes from one step to the next as SB3's ``predict`` passes it.

    :param predict: SB3's ``predict`` of the policy; ``None`` for uniform random actions.
    :param action_space: the env's action space.
    :param noise_scale: standard deviation of the Gaussian noise on each action component; ``None`` for none.
    :param controller: the PD controller behind ``predict``, seeded at each episode's start.
    """

    def __init__(
        self,
        predict: Callable[..., tuple[np.ndarray, Any]] | None,
        action_space: gym.spaces.Box,
        noise_scale: np.ndarray | None = None,
        controller: envs.PDController | None = None,
    ) -> None:
        self.predict = predict
        self.action_space = action_space
        self.noise_scale = noise_scale
        self.controller = controller
        self._state: Any = None
        self._episode_start = True

    def start(self, seed: int, index: int) -> None:
        """Begin episode ``index`` of a collection from ``seed``: a new state, and the PD controller's random yaws
        seeded with ``(seed, index)`` (``PDController.seed``), so that they do not depend on the workers."""
        self._state, self._episode_start = None, True
        if self.controller is not None:
            self.controller.seed((seed, index))

    def __call__(self, observation: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
        space = self.action_space
        if self.predict is None:
            return rng.uniform(space.low, space.high).astype(np.float32), None
        episode_start = np.array([self._episode_start])
        clean, self._state = self.predict(observation, self._state, episode_start, deterministic=True)
        self._episode_start = False
        if self.noise_scale is None:
            return clean, None
        executed = np.clip(clean + self.noise_scale * rng.standard_normal(self.noise_scale.shape), space.low, space.high)
        return executed.astype(np.float32), clean


def make_policy(spec: CollectionSpec, env: gym.Env) -> BehaviourPolicy:
    """The behaviour policy of ``spec`` for ``env``."""
    action_space = env.action_space
    if spec.policy == "random":
        return BehaviourPolicy(None, action_space)
    controller = None
    if spec.controller is not None:
        controller = envs.PDController.for_env(env, **envs.CONTROLLERS[spec.controller])
        predict = controller.predict
    else:
        from rl_zoo3.utils import ALGOS

        if spec.algo not in ALGOS:
            raise ValueError(f"unknown algo {spec.algo!r} for the model policy {spec.policy}: one of {sorted(ALGOS)}")
        try:
            model = ALGOS[spec.algo].load(spec.policy, device="cpu")
        except Exception as error:
            raise ValueError(f"cannot load {spec.policy} as a {spec.algo} model: {error}") from error
        if model.action_space != action_space:  # another action mode: its actions would mean other things here
            from sb3_cql.evaluate import env_kwargs_for

            env_kwargs_for(model, spec.env_id, {**spec.env_kwargs, "action_mode": spec.action_mode})  # says how
            raise ValueError(f"the model {spec.policy}'s action space {model.action_space} is not {spec.env_id}'s "
                             f"{action_space}")  # fmt: skip
        predict = model.predict
    if spec.noise == 0:
        return BehaviourPolicy(predict, action_space, controller=controller)
    unwrapped = env.unwrapped
    # Noise is specified on the arm's joint targets (rad); a delta action moves a target by arm_max_delta.
    scale = np.zeros(action_space.shape, dtype=np.float64)
    n_arm = len(envs.robot.ARM_JOINTS)
    scale[:n_arm] = spec.noise / (unwrapped.config.arm_max_delta if unwrapped.action_mode == "delta" else 1.0)
    return BehaviourPolicy(predict, action_space, scale, controller)


def model_action_mode(model_path: str, algo: str | None, env_id: str, given: str | None = None) -> str | None:
    """The action mode a saved SB3 model acts in on ``env_id`` (the mode whose action space is the model's), as
    ``python -m sb3_cql.evaluate`` finds it; ``given`` is checked against it (a ``ValueError`` if it is another).
    ``given`` where the model's spaces cannot be read (:func:`make_policy` then says why it cannot be loaded)."""
    from types import SimpleNamespace

    from rl_zoo3.utils import ALGOS
    from stable_baselines3.common.save_util import load_from_zip_file

    from sb3_cql.evaluate import env_kwargs_for

    if algo not in ALGOS:
        return given
    try:
        data, _, _ = load_from_zip_file(model_path, device="cpu", load_data=True)
        spaces = SimpleNamespace(observation_space=data["observation_space"], action_space=data["action_space"])
    except Exception:
        return given
    return env_kwargs_for(spaces, env_id, {"action_mode": given} if given else {})["action_mode"]


_worker: dict[str, Any] = {}


def _init_worker(spec: CollectionSpec) -> None:
    env = gym.make(spec.env_id, **spec.env_kwargs)
    _worker.update(spec=spec, env=env, policy=make_policy(spec, env))


def _init_pool_worker(spec: CollectionSpec, parent: int) -> None:
    """Set up a worker process. Ctrl-C reaches every process of the terminal's group, SIGTERM may too: a worker
    ignores both (no traceback from them), and the parent stops the collection and its workers. The worker started
    with them blocked (:func:`_interrupts_blocked`), so one sent before this point is dropped too. It dies with the
    parent (:func:`~sb3_cql.interrupts.die_with_parent`): a killed collection leaves no worker behind."""
    die_with_parent(parent)
    for signum in INTERRUPTS:
        signal.signal(signum, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, set(INTERRUPTS))
    _init_worker(spec)


def _run_episode(index: int) -> EpisodeBuffer:
    """Roll out episode ``index`` of the worker's collection."""
    spec, env, policy = _worker["spec"], _worker["env"], _worker["policy"]
    rng = np.random.default_rng((spec.seed, index))
    observation, _ = env.reset(seed=spec.seed + index)
    policy.start(spec.seed, index)
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


def _run_episodes(spec: CollectionSpec, indices: list[int]) -> list[EpisodeBuffer]:
    """Roll out the episodes ``indices`` of ``spec`` in this process (a Ray task: the env and policy of its process are
    kept for the next task of the same collection)."""
    if _worker.get("spec") != spec:
        if "env" in _worker:
            _worker["env"].close()
        _init_worker(spec)
    return [_run_episode(index) for index in indices]


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
    """The episodes ``indices`` in order, from ``workers`` processes (in this one if 1), or from Ray tasks of ``chunk``
    episodes each on the cluster at ``ray_address`` (:func:`sb3_cql.cluster.run_in_order`; a task whose node dies is
    run again: the episodes do not depend on where they run)."""
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
    # spawn, not fork: a parent holding torch threads or a PyBullet client must not be copied. An executor, not
    # a Pool: a killed worker raises BrokenProcessPool instead of hanging the collection.
    executor = ProcessPoolExecutor(workers, multiprocessing.get_context("spawn"), _init_pool_worker, (spec, os.getpid()))
    finished = False
    try:
        # One episode a task (an episode takes 0.1 to 1 s, a task's messages ~1 ms): every episode finished in order
        # reaches this process, to be kept if the collection is interrupted.
        with _interrupts_blocked():  # the workers start (at the first submissions) with them blocked, until they ignore them
            futures = deque(executor.submit(_run_episode, index) for index in indices)
        while futures:  # each episode let go once handed over: the collection holds no more than the workers' lead
            yield futures.popleft().result()
        finished = True
    except BrokenProcessPool as error:
        raise RuntimeError(
            f"a collection worker died (killed, or out of memory); the episodes written so far are kept and "
            f"running the same collection again resumes it: {error}"
        ) from error
    finally:
        if finished:
            executor.shutdown(wait=False)
        else:  # interrupted or failed: the episodes in progress are not kept, their workers are stopped
            with _interrupts_deferred(reraise=False):  # a second Ctrl-C meanwhile changes nothing
                _stop_workers(executor)


def _stop_workers(executor: ProcessPoolExecutor) -> None:
    """Shut ``executor`` down without waiting for its tasks: kill its workers (they ignore SIGTERM), then wait for the
    executor to
    fail the pending futures and close its pipes. No future is cancelled first: in Python 3.11, the executor's thread
    raises InvalidStateError on a cancelled one when it finds its workers gone, and exiting before that thread is done
    can write to a pipe it closes (EBADF)."""
    for process in list((getattr(executor, "_processes", None) or {}).values()):
        process.kill()
    executor.shutdown(wait=True)


#: The signals that stop a collection as Ctrl-C does: SIGINT and SIGTERM (``kill PID``).
INTERRUPTS = (signal.SIGINT, signal.SIGTERM)


def _interrupt(signum: int) -> KeyboardInterrupt:
    """The ``KeyboardInterrupt`` a signal of :data:`INTERRUPTS` raises; a SIGTERM's is marked ``terminated`` (exit
    status 143: :func:`sb3_cql.interrupts.exit_status`)."""
    interrupt = KeyboardInterrupt()
    if signum == signal.SIGTERM:
        interrupt.terminated = True  # type: ignore[attr-defined]
    return interrupt


def _handles(signum: int, previous: Any) -> bool:
    """Whether a collection handles ``signum`` whose handler was ``previous``: Ctrl-C where Python raises
    ``KeyboardInterrupt`` (or a handler of the caller's), SIGTERM where it still has its default (or a handler)."""
    return callable(previous) or (signum == signal.SIGTERM and previous == signal.SIG_DFL)


def _raise_as_before(signum: int, previous: Any, frame: Any) -> None:
    """What ``signum`` did with its ``previous`` handler: call it, or raise ``KeyboardInterrupt`` for a default one."""
    if callable(previous):
        previous(signum, frame)
    elif previous == signal.SIG_DFL:
        raise _interrupt(signum)


@contextlib.contextmanager
def _interrupts_blocked() -> Iterator[None]:
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


@contextlib.contextmanager
def _interrupts_noted() -> Iterator[Callable[[], int]]:
    """Raise ``KeyboardInterrupt`` on Ctrl-C as the handler there was does (and on SIGTERM, which would end the process
    without a word), and note it: the block gets a function telling whether one came. Python drops an exception
    raised in a ``__del__`` (PyBullet's ``BulletClient`` disconnects in one, which a garbage collection can run at any
    moment), so a loop that checks the note still stops: the function gives the first signal noted, 0 for none.
    Only the main thread receives signals; elsewhere, or with the signals ignored, nothing is noted."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: 0
        return
    noted: list[int] = []
    previous = {signum: signal.getsignal(signum) for signum in INTERRUPTS}

    def note(signum: int, frame: Any) -> None:
        noted.append(signum)
        _raise_as_before(signum, previous[signum], frame)

    for signum, handler in previous.items():
        if _handles(signum, handler):
            signal.signal(signum, note)
    try:
        yield lambda: noted[0] if noted else 0
    finally:
        for signum, handler in previous.items():
            if _handles(signum, handler):
                signal.signal(signum, handler)


@contextlib.contextmanager
def _interrupts_deferred(reraise: bool = True) -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM back until the block is done, so that a write is never cut in half, then do what the
    first that came would have done (raise ``KeyboardInterrupt``, or call the handler there was) if ``reraise``.
    Only the main thread receives signals: in another one, the block just runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in INTERRUPTS}
    received: list[tuple[int, Any]] = []
    for signum, handler in previous.items():
        if _handles(signum, handler):
            signal.signal(signum, lambda signum, frame: received.append((signum, frame)))
    try:
        yield
    finally:
        for signum, handler in previous.items():
            if _handles(signum, handler):
                signal.signal(signum, handler)
    if received and reraise:
        signum, frame = received[0]
        _raise_as_before(signum, previous[signum], frame)


def estimate(spec: CollectionSpec, n_episodes: int, workers: int) -> tuple[int, float | None, int]:
    """About how many transitions, seconds and bytes of disk ``n_episodes`` episodes of ``spec`` take with
    ``workers`` processes (one per CPU at most), at the speeds measured on this project's 2-core machine: from
    :data:`EPISODE_STEPS`, :data:`TRANSITIONS_PER_S`, :data:`WORKER_START_S` and the disk constants. A model policy's
    episodes are counted at the time limit (at most) and its time is ``None``."""
    steps = EPISODE_STEPS.get(spec.env_id, {}).get(spec.policy, envs.MAX_EPISODE_STEPS)
    transitions = n_episodes * steps
    seconds = None
    if spec.policy in POLICIES:
        rate = TRANSITIONS_PER_S["random" if spec.policy == "random" else "controller"]
        seconds = WORKER_START_S + transitions / (rate * max(1, min(workers, os.cpu_count() or 1, n_episodes)))
    per_transition = BYTES_PER_TRANSITION + (CLEAN_ACTION_BYTES_PER_TRANSITION if spec.noise else 0)
    return transitions, seconds, n_episodes * BYTES_PER_EPISODE + transitions * per_transition


def _plan(spec: CollectionSpec, dataset_id: str, workers: int, start: int, where: str | None = None) -> str:
    """The line a collection prints before it starts (``start`` episodes already collected; ``where`` says where the
    episodes run, ``workers`` local processes by default)."""
    remaining = spec.n_episodes - start
    transitions, seconds, size = estimate(spec, remaining, workers)
    if seconds is None:
        cost = f"at most {_size(size)} of disk ({transitions:,} transitions); a model policy's time is not estimated"
    else:
        cost = f"about {_duration(seconds)} and {_size(size)} of disk ({transitions:,} transitions)"
    with_workers = where or f"with {workers} worker{'s' if workers > 1 else ''}"
    if start == 0:
        return f"collecting {dataset_id}: {spec.n_episodes} episodes {with_workers}, {cost}"
    if remaining == 0:
        return f"resuming {dataset_id}: {start} of {spec.n_episodes} episodes already collected, none left"
    return (
        f"resuming {dataset_id}: {start} of {spec.n_episodes} episodes already collected; "
        f"the other {remaining} {with_workers}, {cost}"
    )


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, round(seconds))} s"
    if seconds < 90 * 60:
        return f"{round(seconds / 60)} min"
    return f"{seconds / 3600:.1f} h"


def _size(size: float) -> str:
    if size < 1e6:
        return f"{max(1, round(size / 1e3))} kB"
    if size < 1e9:
        return f"{round(size / 1e6)} MB"
    return f"{size / 1e9:.1f} GB"


def _resume(files: DatasetFiles, spec: CollectionSpec, overwrite: bool) -> tuple[set[int], list[bool]]:
    """The episodes (indices) an interrupted collection of ``spec`` holds, and their successes; a new collection
    where there is none. A partial collection of another spec, or one with a file that cannot be read, is refused
    with one :class:`DatasetError` saying what it holds and what to do (``overwrite`` replaces it)."""
    files.check_writable()
    held_spec = files.spec()
    if files.holds_anything() and held_spec != spec.to_json():
        if not overwrite and not files.holds_no_episodes():  # one that kept none is replaced: nothing is lost
            raise DatasetError(_other_collection(files, held_spec))
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


def _other_collection(files: DatasetFiles, held_spec: str | None) -> str:
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


def _check_space(files: DatasetFiles, needed: int, what: str) -> None:
    """One :class:`DatasetError` if the dataset's folder has less than ``needed`` bytes free."""
    folder = files.final.parent
    free = shutil.disk_usage(folder).free
    if free < needed:
        raise DatasetError(
            f"not enough disk space in {folder} for {what}: about {_size(needed)} needed, {_size(free)} free; "
            f"free some space (or set MINARI_DATASETS_PATH to another disk) and run the same command"
            + (f" (the {files.episodes_held()} episodes collected are kept)" if files.episodes_held() else "")
        )


def _assemble(files: DatasetFiles, env: gym.Env, metadata: Callable[[list[bool]], dict[str, Any]]) -> None:
    """Build the Minari dataset from the collection's episode files in ``assembling/``, with ``metadata(successes)``,
    and rename it to ``assembled/`` once complete (built again from the files after a kill)."""
    shutil.rmtree(files.assembling, ignore_errors=True)
    if files.assembled.is_dir():  # complete already: a kill came after it was built
        return
    episode_files = files.episode_files()
    data_bytes = sum(path.stat().st_size for _, path in episode_files)
    _check_space(files, data_bytes + sum(map(len, (i for i, _ in episode_files))) * BYTES_PER_EPISODE, "its assembly")
    files.assembling.mkdir()
    # With the spaces given, Minari makes no env of its own to read them (one it would drop at once: a PyBullet
    # client's __del__, which drops a Ctrl-C that arrives while it disconnects).
    storage = MinariStorage.new(files.assembling / "data", env.observation_space, env.action_space, env.spec,
                                data_format="hdf5")  # fmt: skip
    successes = []
    try:
        for _, path in episode_files:
            episodes = files.read_episodes(path)
            storage.update_episodes(episodes)
            successes += [bool(episode.rewards[-1] > 0) for episode in episodes]
            crash_point("assemble")
        storage.update_metadata(metadata(successes))
    except OSError as error:
        shutil.rmtree(files.assembling, ignore_errors=True)
        raise DatasetError(
            f"cannot write the dataset {files.dataset_id} in {files.assembling}: {' '.join(str(error).split())}; "
            f"its {files.episodes_held()} episodes are kept in {files.episodes}, and the same command assembles it"
        ) from None
    os.replace(files.assembling, files.assembled)
    crash_point("assembled")


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
    whole or not at all; once all are there they are assembled into the dataset, which is renamed into place
    (:mod:`sb3_cql.data.partial` has the layout). A kill at any instant leaves no dataset under its id, or the
    complete one, and running the same collection again resumes it to the dataset an uninterrupted run gives. A
    partial collection of another spec is kept, and this one refused with a :class:`DatasetError` saying what it
    holds (``overwrite`` replaces it), unless it kept no episode; so is a second collection of the id while one runs.
    A standard id (:func:`standard_collection`) takes its standard collection only, or its first episodes: another
    policy, seed, noise or physics is a :class:`DatasetError` naming an id of its own. Actions are the executed
    ones; with noise, the policy's clean actions are in the episodes' ``infos["clean_action"]``.

    It prints (on stderr) one line before it starts: the episodes, the workers and about how long and how much disk
    they take, or, resuming, how many episodes it already has; it refuses to start on a disk without room for them.
    On Ctrl-C or SIGTERM (``KeyboardInterrupt``), it writes the episodes finished so far, prints one line saying how
    many are kept, and raises the ``KeyboardInterrupt`` again.

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
    policy_name = spec.policy if spec.policy in POLICIES else Path(spec.policy).stem
    in_thousands = spec.n_episodes >= 1000 and spec.n_episodes % 1000 == 0
    dataset_id = dataset_id or ids.dataset_id(spec.env_id, policy_name, spec.action_mode,
                                              episodes=spec.n_episodes if in_thousands else None)  # fmt: skip
    _check_standard(spec, dataset_id)
    write_every = WRITE_EVERY if write_every is None else write_every
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if write_every < 1:
        raise ValueError(f"write_every must be >= 1, got {write_every}")
    files = DatasetFiles(dataset_id)
    with files.locked():
        files.recover()
        _prepare(dataset_id, overwrite)
        return _collect(spec, files, workers, overwrite, progress_bar, write_every, ray_address)


def _collect(
    spec: CollectionSpec,
    files: DatasetFiles,
    workers: int,
    overwrite: bool,
    progress_bar: bool,
    write_every: int,
    ray_address: str | None,
) -> MinariDataset:
    """:func:`collect_dataset` holding the dataset's lock."""
    dataset_id = files.dataset_id
    env, pending, published, held = None, [], False, 0
    try:
        env = gym.make(spec.env_id, **spec.env_kwargs)
        if spec.controller is None and spec.policy != "random":
            make_policy(spec, env)  # a model that cannot be loaded, or acts in another action mode, fails here
        # Before anything is written: a disk without room, or a cluster out of reach, is one line that leaves nothing.
        left = spec.n_episodes - (files.episodes_held() if files.spec() == spec.to_json() else 0)
        where = None
        if left > 0:
            _, _, size = estimate(spec, left, workers)
            _, _, total = estimate(spec, spec.n_episodes, workers)
            _check_space(files, size + total, f"{left} episodes and the dataset's assembly")
            if ray_address is not None:
                from sb3_cql.cluster import cluster_cpus, connect

                workers = cluster_cpus(connect(ray_address))
                where = f"as Ray tasks on the {workers} CPUs of the cluster at {ray_address}"
        done, successes = _resume(files, spec, overwrite)
        held = len(done)
        missing = [index for index in range(spec.n_episodes) if index not in done]
        print(_plan(spec, dataset_id, workers, held, where), file=sys.stderr, flush=True)
        steps, begin = 0, time.perf_counter()
        with (
            _interrupts_noted() as interrupted,
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
                    raise _interrupt(interrupted())
            held += _write(files, pending)
            if interrupted():
                raise _interrupt(interrupted())
            _assemble(files, env, lambda successes: _metadata(dataset_id, spec, successes, env))
        with _interrupts_deferred():
            final = files.publish()
            published = True
        return MinariDataset(final / "data")
    except KeyboardInterrupt as interrupt:
        with _interrupts_deferred(reraise=False):  # more Ctrl-C while the finished episodes are written change nothing
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
    """Write the ``pending`` episodes as one file, whole even if Ctrl-C comes meanwhile, empty the list and return how
    many were written."""
    with _interrupts_deferred():
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
    """The dataset ``dataset_id``, collected first if it is missing and its id is one of this package's standard
    ones (``sb3cql/<task>/<policy>[-delta][-<N>k]-v0``, :func:`standard_collection`: 10,000 episodes, or N
    thousand, from seed 0). Any other missing id raises :class:`~sb3_cql.data.DatasetError`. An interrupted
    collection resumes; what a collection prints and does on Ctrl-C is :func:`collect_dataset`'s. While another
    process collects the dataset (two trainings started at once on a new machine), this one waits for it, then loads
    it.

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
        _prepare(dataset_id, overwrite=False)
        return _collect(spec, files, workers or os.cpu_count() or 1, False, progress_bar, WRITE_EVERY, None)


def standard_collection(dataset_id: str) -> CollectionSpec | None:
    """The collection a standard id stands for (``sb3cql/<task>/<policy>[-delta][-<N>k]-v0`` with a named policy
    and a registered task: its episodes, 10,000 without ``-<N>k``, from seed 0, the policy's default noise), or
    ``None`` for any other id. A ``-<N>k`` dataset holds the first episodes of the 10,000-episode one (episode ``i``
    is reset with seed ``i``)."""
    parsed = ids.parse_dataset_id(dataset_id)
    if parsed is None or parsed[3] != 0 or parsed[0] not in envs.ENV_IDS:
        return None
    env_id, policy, action_mode, _, episodes = parsed
    env_kwargs = {"action_mode": action_mode} if action_mode != "absolute" else {}
    return CollectionSpec(env_id, policy, n_episodes=episodes, env_kwargs=env_kwargs)


def _check_standard(spec: CollectionSpec, dataset_id: str) -> None:
    """A :class:`DatasetError` if ``dataset_id`` is a standard id (:func:`standard_collection`) and ``spec`` is not its
    collection, or the first episodes of it: what trains on the id would get other data without a word."""
    standard = standard_collection(dataset_id)
    if standard is None:
        return
    fields = ("policy", "seed", "noise", "env_kwargs", "algo")
    differs = [name for name in fields if getattr(spec, name) != getattr(standard, name)]
    if spec.n_episodes > standard.n_episodes:
        differs.append("n_episodes")
    if differs:
        given = ", ".join(f"{name} {getattr(spec, name)!r}" for name in differs)
        defined = ", ".join(f"{name} {getattr(standard, name)!r}" for name in differs)
        own = dataset_id.rsplit("-v", 1)[0] + "-custom-v0"
        raise DatasetError(
            f"{dataset_id} is a standard dataset id, defined as {standard.n_episodes} episodes or its first ones with "
            f"{defined}; this collection has {given}: give it an id of its own, e.g. --dataset-id {own}"
        )


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
        _prepare(dataset_id, overwrite)
        sources = [load_dataset(source) for source in source_ids]
        try:
            env_spec = validate_datasets_to_combine(sources)
        except ValueError:  # Minari's message names env specs, not what differs
            made = "; ".join(f"{source_id}: {_made_in(source)}" for source_id, source in zip(source_ids, sources, strict=True))
            raise DatasetError(f"cannot mix datasets of different envs or action modes ({made}): mix datasets of one env "
                               "and action mode") from None  # fmt: skip
        if files.holds_anything():
            if not overwrite:
                raise DatasetError(_other_collection(files, files.spec()))
            shutil.rmtree(files.partial)
        files.assembling.mkdir(parents=True)
        storage = MinariStorage.new(files.assembling / "data", env_spec=env_spec, data_format="hdf5")
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
                **{key: sources[0].storage.metadata[key] for key in METADATA_OF_THE_FIRST},
            }
        )
        os.replace(files.assembling, files.assembled)
        with _interrupts_deferred():
            return MinariDataset(files.publish() / "data")


def _prepare(dataset_id: str, overwrite: bool) -> Path:
    """The folder of ``dataset_id``, after checking it may be written and creating its Minari namespace. A dataset
    there is a ``FileExistsError`` unless ``overwrite``; a damaged one (no ``metadata.json``) a
    :class:`DatasetError`, as :func:`~sb3_cql.data.load_dataset` has it."""
    final = ids.dataset_path(dataset_id)
    if final.exists() and not overwrite:
        if not ids.dataset_exists(dataset_id):
            raise DatasetError(damaged_dataset(dataset_id))
        raise FileExistsError(f"dataset {dataset_id} already exists at {final}: pass overwrite=True (--overwrite)")
    namespace = parse_dataset_id(dataset_id)[0]
    if namespace is not None and namespace not in list_local_namespaces():
        create_namespace(namespace, description="Panda grasping datasets written by sb3-cql")
    return final


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
            parameters = controller.parameters()
        finally:
            controller.close()
        if controller.yaw == "random":
            parameters["yaw_episode_seed"] = f"episode i: PDController.seed(({spec.seed}, i))"
        metadata["controller"] = json.dumps(parameters)
    return metadata
