"""Rollouts of a behaviour policy: what a dataset is made of (:class:`CollectionSpec`), the behaviour policies, and one
episode of a collection in a worker process. Episode ``i`` is reset with ``seed + i`` and draws its noise and a PD
controller's random yaws from ``(seed, i)``, so a dataset does not depend on the number of workers.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from minari.data_collector import EpisodeBuffer

import envs
from envs.pd_controller import REFERENCE_CONTROLLERS
from sb3_cql.data.ids import POLICIES, RANDOM_POLICY, default_noise, noisy_policies
from sb3_cql.data.spaces import check_spaces, env_kwargs_for, env_name


@dataclasses.dataclass(frozen=True)
class CollectionSpec:
    """What a dataset is made of; two collections with equal specs write identical data.

    :param env_id: gymnasium id of the task.
    :param policy: ``"pid"``, ``"noisy"`` (PD with Gaussian noise on the executed arm targets), ``"pid-regrasp"``
        and ``"noisy-regrasp"`` (grasping a lost object again), ``"pid-regrasp-yaw"`` and ``"noisy-regrasp-yaw"``
        (the hand's yaw drawn at random at each attempt), ``"random"`` (uniform actions), or a saved SB3 model's path.
    :param n_episodes: number of episodes.
    :param seed: episode ``i`` is reset with ``seed + i`` (an integer >= 0).
    :param noise: standard deviation (rad) of the noise on the executed arm joint targets; ``None``: 0.03 for the noisy
        policies, 0 otherwise.
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
            object.__setattr__(self, "noise", default_noise(self.policy))
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float)) or not 0 <= self.noise < float("inf"):
            raise ValueError(f"noise must be a finite number >= 0 (std in rad), got {self.noise!r}")

    @property
    def controller(self) -> str | None:
        """The name of the PD controller behind the policy (a key of ``envs.CONTROLLERS``), if it is one."""
        name = noisy_policies().get(self.policy, self.policy)
        return name if name in envs.CONTROLLERS else None

    @property
    def action_mode(self) -> str:
        return self.env_kwargs.get("action_mode", "absolute")

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)


class BehaviourPolicy:
    """The behaviour policy of a collection in one env: :meth:`start` before each episode, then one call a step,
    ``policy(observation, rng) -> (executed action, clean action before noise or None)``, ``rng`` the episode's noise
    generator: ``predict`` (SB3's; ``None`` for uniform random actions) plus Gaussian noise of ``noise_scale`` per
    action component, if any. ``controller``, the PD controller behind ``predict``, is seeded at each episode's start.
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
        """Begin episode ``index`` of a collection from ``seed``: a new state, the PD controller seeded with
        ``(seed, index)``."""
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
    if spec.policy == RANDOM_POLICY:
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
        try:
            check_spaces(model, env.observation_space, action_space, env_name(env, spec.env_id))
        except ValueError as error:  # another task's or action mode's model: its actions would mean other things here
            env_kwargs_for(model, spec.env_id, {**spec.env_kwargs, "action_mode": spec.action_mode})  # says which mode
            raise ValueError(f"{spec.policy}: {error}") from None
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
    """The action mode a saved SB3 model acts in on ``env_id``, ``given`` checked against it (``ValueError``);
    ``given`` where the model's spaces cannot be read."""
    from types import SimpleNamespace

    from rl_zoo3.utils import ALGOS
    from stable_baselines3.common.save_util import load_from_zip_file

    if algo not in ALGOS:
        return given
    try:
        data, _, _ = load_from_zip_file(model_path, device="cpu", load_data=True)
        spaces = SimpleNamespace(observation_space=data["observation_space"], action_space=data["action_space"])
    except Exception:
        return given
    return env_kwargs_for(spaces, env_id, {"action_mode": given} if given else {})["action_mode"]


#: The spec, env and behaviour policy of the collection this process rolls out (:func:`_init_worker`).
_worker: dict[str, Any] = {}


def _init_worker(spec: CollectionSpec) -> None:
    """Make this process the roller-out of ``spec``: its env and behaviour policy."""
    env = gym.make(spec.env_id, **spec.env_kwargs)
    _worker.update(spec=spec, env=env, policy=make_policy(spec, env))


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
    """Roll out the episodes ``indices`` of ``spec`` (a Ray task: the process keeps its env and policy for the next)."""
    if _worker.get("spec") != spec:
        if "env" in _worker:
            _worker["env"].close()
        _init_worker(spec)
    return [_run_episode(index) for index in indices]
