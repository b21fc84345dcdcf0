"""Names and places of the datasets: one home for the dataset id scheme."""

from __future__ import annotations

import re
from pathlib import Path

from minari.storage import get_dataset_path

#: Minari namespace of every dataset this package writes.
NAMESPACE = "sb3cql"
#: Behaviour policies that :func:`~sb3_cql.data.collect_dataset` knows by name: the PD controllers
#: (``envs.CONTROLLERS``: ``pid``, and ``pid-regrasp`` that grasps a lost object again), each with Gaussian noise on
#: its arm targets (``noisy``, ``noisy-regrasp``), and uniform random actions.
POLICIES = ("pid", "noisy", "pid-regrasp", "noisy-regrasp", "random")
#: The noisy policies and the PD controller under each one's noise.
NOISY_POLICIES = {"noisy": "pid", "noisy-regrasp": "pid-regrasp"}
#: Standard deviation (rad) of the Gaussian noise the ``noisy`` policy adds to the PD controller's arm targets.
DEFAULT_NOISE = 0.03


def dataset_id(env_id: str, policy: str = "pid", action_mode: str = "absolute", version: int = 0) -> str:
    """The Minari id of a dataset: ``sb3cql/Panda-v0/pid-v0``, ``sb3cql/Panda-v0/noisy-delta-v0``, ...

    :param env_id: the gymnasium id of the task the data comes from.
    :param policy: the behaviour policy's name (``pid``, ``noisy``, ``random``, ``mixed`` or any name).
    :param action_mode: the env's action mode; datasets of the two modes hold different actions.
    :param version: the dataset version.
    """
    suffix = "" if action_mode == "absolute" else f"-{action_mode}"
    return f"{NAMESPACE}/{env_id}/{policy}{suffix}-v{version}"


def dataset_path(dataset_id: str) -> Path:
    """Where Minari keeps ``dataset_id`` (under ``MINARI_DATASETS_PATH``, or ``~/.minari/datasets``)."""
    return get_dataset_path(dataset_id)


def dataset_exists(dataset_id: str) -> bool:
    """Whether ``dataset_id`` is a complete dataset on disk (Minari writes ``metadata.json`` last)."""
    return (dataset_path(dataset_id) / "data" / "metadata.json").exists()


def parse_dataset_id(dataset_id: str) -> tuple[str, str, str, int] | None:
    """``(env_id, policy, action_mode, version)`` of an id made by :func:`dataset_id` with a named policy, else
    ``None``: ``sb3cql/Panda-v0/noisy-delta-v0`` -> ``("Panda-v0", "noisy", "delta", 0)``."""
    policies = "|".join(POLICIES)
    match = re.fullmatch(rf"{NAMESPACE}/([^/]+)/({policies})(-delta)?-v(\d+)", dataset_id)
    if match is None:
        return None
    env_id, policy, delta, version = match.groups()
    return env_id, policy, "delta" if delta else "absolute", int(version)
