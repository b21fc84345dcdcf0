"""What the package registers with RL-Zoo3, as ``rl_zoo3/train_sbx.py`` registers its algorithms: ``cql``, ``bc`` and
``iql`` in ``ALGOS``, the Panda tasks, the CQL and IQL search spaces, and our ``hyperparams/`` files as the default
config of our algorithms and tasks."""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType

import yaml

#: The algorithm the package adds to the zoo, with its search space.
ALGO = "cql"
#: Every algorithm the package adds: our config file is their default config on any env.
ALGOS = (ALGO, "bc", "iql")


def hyperparams_dir() -> Path:
    """Our zoo config files: ``hyperparams/`` of the source tree (editable installs), else the installed copy."""
    source_tree, installed = Path(__file__).resolve().parents[2], Path(sys.prefix) / "share" / "sb3-cql"
    for folder in (source_tree / "hyperparams", installed / "hyperparams"):
        if (folder / f"{ALGO}.yml").is_file():
            return folder
    raise FileNotFoundError("sb3-cql's hyperparams/ folder is missing: reinstall the package")


def config_file(algo: str, env_id: str) -> Path | None:
    """Our config for ``algo`` on ``env_id``: always for our algorithms, for others when our file has the env."""
    path = hyperparams_dir() / f"{algo}.yml"
    if not path.is_file():
        return None
    if algo in ALGOS:
        return path
    with open(path) as file:
        return path if env_id in (yaml.safe_load(file) or {}) else None


def our_config(config: str) -> str:
    """``config`` (``--conf-file``), or where it names one of our files that is not there (``cql_finetune.yml``
    outside the source tree), our installed copy of it."""
    ours = hyperparams_dir() / Path(config).name
    return str(ours) if not Path(config).exists() and ours.is_file() else config


def register_algorithms(utils: ModuleType) -> None:
    """Our algorithms in ``rl_zoo3.utils.ALGOS`` (``--algo``'s choices), and the tasks' gymnasium ids."""
    import envs  # noqa: F401  (registers the tasks; imported with the zoo, not before: it loads PyBullet)
    from sb3_cql.bc import BC
    from sb3_cql.cql import CQL
    from sb3_cql.iql import IQL

    for name, algorithm in zip(ALGOS, (CQL, BC, IQL), strict=True):
        utils.ALGOS.setdefault(name, algorithm)


def register_search_spaces(hyperparams_opt: ModuleType) -> None:
    """CQL's and IQL's samplers and converters for ``-optimize``."""
    from sb3_cql.zoo.search_space import convert_cql_params, convert_iql_params, sample_cql_params, sample_iql_params

    hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault(ALGO, sample_cql_params)
    hyperparams_opt.HYPERPARAMS_CONVERTER.setdefault(ALGO, convert_cql_params)
    hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault("iql", sample_iql_params)
    hyperparams_opt.HYPERPARAMS_CONVERTER.setdefault("iql", convert_iql_params)
