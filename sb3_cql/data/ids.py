"""Names and places of the datasets: the dataset id scheme, and the behaviour policies' names the standard ids are
made of. Those come from the PD controllers the tasks register, read on first use (:func:`behaviour_policies`,
``POLICIES``, ``NOISY_POLICIES``): loading a dataset imports no simulator.
"""

from __future__ import annotations

import functools
import re
import shlex
from pathlib import Path
from typing import Any

from minari.storage import get_dataset_path

from sb3_cql.data.errors import DatasetError

#: Minari namespace of every dataset this package writes.
NAMESPACE = "sb3cql"
#: The behaviour policy of uniform random actions.
RANDOM_POLICY = "random"
#: Standard deviation (rad) of the Gaussian noise the ``noisy`` policy adds to the PD controller's arm targets.
DEFAULT_NOISE = 0.03
#: Name of the file describing a collection in progress, in its ``.partial`` folder (to resume only the same one).
SPEC_FILE = "collection.json"
#: Episodes of a standard dataset whose id gives no count (``sb3cql/Panda-v0/pid-v0``): the thesis's dataset size.
STANDARD_EPISODES = 10_000


def dataset_id(
    env_id: str, policy: str = "pid", action_mode: str = "absolute", version: int = 0, episodes: int | None = None
) -> str:
    """The Minari id of a dataset: ``sb3cql/Panda-v0/pid-v0``, ``sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0`` (1,000
    episodes), ... ``policy`` is any name; ``episodes``, a multiple of 1,000, is written in the id (``-1k``) unless
    ``None`` or :data:`STANDARD_EPISODES`."""
    suffix = "" if action_mode == "absolute" else f"-{action_mode}"
    if episodes is not None and episodes != STANDARD_EPISODES:
        if episodes < 1000 or episodes % 1000:
            raise ValueError(f"a dataset id gives its episodes in thousands, got {episodes}")
        suffix += f"-{episodes // 1000}k"
    return f"{NAMESPACE}/{env_id}/{policy}{suffix}-v{version}"


def check_dataset_id(dataset_id: Any) -> None:
    """A :class:`~sb3_cql.data.DatasetError` unless ``dataset_id`` is an id as Minari takes it,
    ``[NAMESPACE/]NAME-vVERSION``, whose folder is inside the datasets folder (no empty, ``.`` or ``..`` part)."""
    valid = isinstance(dataset_id, str) and re.fullmatch(r"[\w:.\-/]*[\w:.\-]-v\d+", dataset_id) is not None
    if not valid or any(part in ("", ".", "..") for part in dataset_id.split("/")):
        raise DatasetError(f"{dataset_id!r} is not a dataset id: write [NAMESPACE/]NAME-vVERSION, a version at the end and "
                           f"no '..' (e.g. {NAMESPACE}/Panda-v0/pid-v0)")  # fmt: skip


def dataset_path(dataset_id: str) -> Path:
    """Where Minari keeps ``dataset_id`` (under ``MINARI_DATASETS_PATH``, or ``~/.minari/datasets``); an id that is
    not one (:func:`check_dataset_id`) is a :class:`~sb3_cql.data.DatasetError`."""
    check_dataset_id(dataset_id)
    return get_dataset_path(dataset_id)


def partial_path(dataset_id: str) -> Path:
    """Where a collection of ``dataset_id`` writes until it is complete: a hidden ``.<name>.partial`` folder beside
    the dataset's."""
    final = dataset_path(dataset_id)
    return final.with_name(f".{final.name}.partial")


def collect_command(spec: dict[str, Any], dataset_id: str) -> str | None:
    """The ``python -m sb3_cql.data collect`` command line of a collection, from its spec's fields (as
    :meth:`~sb3_cql.data.CollectionSpec.to_json` writes them), or ``None`` if it cannot express it (physics keywords)."""
    env_kwargs = dict(spec.get("env_kwargs") or {})
    action_mode = env_kwargs.pop("action_mode", "absolute")
    if env_kwargs:
        return None
    words = ["python", "-m", "sb3_cql.data", "collect", "--env", spec["env_id"], "--policy", spec["policy"]]
    if spec.get("algo") is not None:
        words += ["--algo", spec["algo"]]
    words += ["--episodes", str(spec["n_episodes"]), "--seed", str(spec["seed"])]
    if spec.get("noise") != default_noise(spec["policy"]):
        words += ["--noise", str(spec["noise"])]
    if action_mode != "absolute":
        words += ["--action-mode", action_mode]
    return shlex.join([*words, "--dataset-id", dataset_id])


def dataset_exists(dataset_id: str) -> bool:
    """Whether ``dataset_id`` is a complete dataset on disk (Minari writes ``metadata.json`` last)."""
    return (dataset_path(dataset_id) / "data" / "metadata.json").exists()


def parse_dataset_id(dataset_id: str) -> tuple[str, str, str, int, int] | None:
    """``(env_id, policy, action_mode, version, episodes)`` of an id made by :func:`dataset_id` with a named policy,
    else ``None``: ``sb3cql/Panda-v0/pid-2k-v0`` -> ``("Panda-v0", "pid", "absolute", 0, 2000)``."""
    policies = "|".join(sorted(behaviour_policies(), key=len, reverse=True))  # a name before any that begins it
    match = re.fullmatch(rf"{NAMESPACE}/([^/]+)/({policies})(-delta)?(?:-([1-9]\d*)k)?-v(\d+)", dataset_id)
    if match is None:
        return None
    env_id, policy, delta, thousands, version = match.groups()
    episodes = STANDARD_EPISODES if thousands is None else 1000 * int(thousands)
    return env_id, policy, "delta" if delta else "absolute", int(version), episodes


def standard_collection_fields(dataset_id: str) -> dict[str, Any] | None:
    """The fields (as :meth:`~sb3_cql.data.CollectionSpec.to_json` writes them) of the collection a standard id stands
    for (``sb3cql/<task>/<policy>[-delta][-<N>k]-v0`` with a named policy and a registered task: its episodes, from
    seed 0, the policy's default noise), or ``None`` for any other id."""
    parsed = parse_dataset_id(dataset_id)
    if parsed is None or parsed[3] != 0 or parsed[0] not in _registered_tasks():
        return None
    env_id, policy, action_mode, _, episodes = parsed
    env_kwargs = {"action_mode": action_mode} if action_mode != "absolute" else {}
    return {"env_id": env_id, "policy": policy, "n_episodes": episodes, "seed": 0, "noise": default_noise(policy),
            "env_kwargs": env_kwargs, "algo": None}  # fmt: skip


def standard_mismatch(dataset_id: str, fields: dict[str, Any], holder: str) -> str | None:
    """Why the collection ``fields`` cannot be the data of ``dataset_id``, a standard id: every field of
    :func:`standard_collection_fields` but the episodes must be its own, and the episodes no more than its own.
    ``None`` where they agree, or for another id. ``holder`` names what holds ``fields`` (``"this collection"``)."""
    standard = standard_collection_fields(dataset_id)
    if standard is None:
        return None
    differs = [name for name in standard if name != "n_episodes" and fields.get(name) != standard[name]]
    if fields.get("n_episodes", 0) > standard["n_episodes"]:
        differs.append("n_episodes")
    if not differs:
        return None
    given = ", ".join(f"{name} {fields.get(name)!r}" for name in differs)
    defined = ", ".join(f"{name} {standard[name]!r}" for name in differs)
    return (f"{dataset_id} is a standard dataset id, defined as {standard['n_episodes']} episodes or its first ones "
            f"with {defined}; {holder} has {given}")  # fmt: skip


def default_noise(policy: str) -> float:
    """The noise (std in rad) of a collection of ``policy`` that gives none: :data:`DEFAULT_NOISE` for a noisy policy."""
    return DEFAULT_NOISE if policy in noisy_policies() else 0.0


def noisy_policy(controller: str) -> str:
    """The policy that adds noise to the PD controller ``controller``: ``pid-regrasp`` -> ``noisy-regrasp``."""
    return "noisy" + controller.removeprefix("pid") if controller.startswith("pid") else f"noisy-{controller}"


@functools.cache
def behaviour_policies() -> tuple[str, ...]:
    """Behaviour policies that :func:`~sb3_cql.data.collect_dataset` knows by name: the PD controllers the tasks register
    as such (``envs.pd_controller.BEHAVIOUR_CONTROLLERS``; not the reference ones, evaluated, never imitated), each
    followed by its noisy policy (:func:`noisy_policy`), and :data:`RANDOM_POLICY`."""
    from envs.pd_controller import BEHAVIOUR_CONTROLLERS  # the tasks and the simulator: see the module's docstring

    return (*(name for controller in BEHAVIOUR_CONTROLLERS for name in (controller, noisy_policy(controller))), RANDOM_POLICY)


@functools.cache
def noisy_policies() -> dict[str, str]:
    """The noisy policies and the PD controller under each one's noise."""
    from envs.pd_controller import BEHAVIOUR_CONTROLLERS

    return {noisy_policy(controller): controller for controller in BEHAVIOUR_CONTROLLERS}


def _registered_tasks() -> dict[str, Any]:
    """The task ids the tasks package registers (``envs.ENV_IDS``)."""
    import envs  # the simulator: see the module's docstring

    return envs.ENV_IDS


def __getattr__(name: str) -> Any:
    # POLICIES and NOISY_POLICIES: the names of behaviour_policies() and noisy_policies(), read on first use.
    if name == "POLICIES":
        return behaviour_policies()
    if name == "NOISY_POLICIES":
        return noisy_policies()
    raise AttributeError(f"module 'sb3_cql.data.ids' has no attribute {name!r}")
