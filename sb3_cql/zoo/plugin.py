"""sb3-cql in RL-Zoo3, registered on import as the zoo's ``train_sbx.py`` registers SBX: our algorithms (and whole
saves for every one), the tasks, our search spaces, and :class:`ExperimentManager`, the zoo's with our configs as the
default and what it lacks where a run would lose data or end in a traceback (what of the zoo it relies on:
:mod:`sb3_cql.zoo.internals`). ``sb3_cql-zoo.pth``'s hook imports this module when ``rl_zoo3`` is imported;
``import sb3_cql.zoo.plugin`` does it by hand."""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import sys
from pathlib import Path
from typing import Any

import yaml
from rl_zoo3 import exp_manager, hyperparams_opt, utils
from rl_zoo3.utils import get_latest_run_id
from stable_baselines3.common.callbacks import CheckpointCallback

import envs  # noqa: F401  (registers the tasks)
from sb3_cql.bc import BC
from sb3_cql.common.atomic import saved_model_problem, with_atomic_saves
from sb3_cql.cql import CQL, CalQL
from sb3_cql.files import os_error_line
from sb3_cql.iql import IQL
from sb3_cql.processes import INTERRUPTED_STATUS, interrupts_noted
from sb3_cql.zoo import errors, search_space

#: Our algorithms' ``--algo`` names, each with its default config in ``hyperparams/`` (Cal-QL's is CQL's).
CONFIGS = {"cql": "cql.yml", "calql": "cql.yml", "bc": "bc.yml", "iql": "iql.yml"}
#: Config keys for what the zoo sets with options only, each with the option and its default in ``rl_zoo3.train``.
OPTIONS = {"eval_freq": ("--eval-freq", 25000), "n_eval_episodes": ("--eval-episodes", 5), "save_freq": ("--save-freq", -1)}


def hyperparams_dir() -> Path:
    """Our zoo configs: ``hyperparams/`` of the source tree (editable installs), else the installed copy."""
    for root in (Path(__file__).resolve().parents[2], Path(sys.prefix) / "share" / "sb3-cql"):
        if (root / "hyperparams" / "cql.yml").is_file():
            return root / "hyperparams"
    raise FileNotFoundError("sb3-cql's hyperparams/ folder is missing: reinstall the package")


def config_file(algo: str, env_id: str) -> Path | None:
    """Our config for ``algo`` on ``env_id``: always for our algorithms, for the zoo's where our file has the env."""
    path = hyperparams_dir() / CONFIGS.get(algo, f"{algo}.yml")
    if not path.is_file() or algo in CONFIGS:
        return path if path.is_file() else None
    return path if env_id in (yaml.safe_load(path.read_text()) or {}) else None


def given_on_command_line(option: str, argv: list[str] | None = None) -> bool:
    """Whether ``argv`` (``rl_zoo3.train``'s, ``sys.argv[1:]``) gives ``option`` as argparse reads it: ``--eval-freq 5``,
    ``--eval-freq=5`` or an abbreviation (``--eval-fr 5``); the zoo keeps values only."""
    words = sys.argv[1:] if argv is None else argv
    return any(word.startswith("--") and len(word) > 2 and option.startswith(word.partition("=")[0]) for word in words)


class ExperimentManager(exp_manager.ExperimentManager):
    """RL-Zoo3's, and: our config as our algorithms' default (and a ``--conf-file`` of ours not in the working folder);
    a config's :data:`OPTIONS` where the option is not given; a config's ``env_kwargs`` for the evaluation env
    and ``args.yml`` too; a run folder of its own; a fine-tuning's checkpoints with their transitions; errors of the
    input on one line, leaving no folder without a model."""

    def __init__(self, args: argparse.Namespace, algo: str, env_id: str, *more: Any, config: str | None = None,
                 **kwargs: Any) -> None:  # fmt: skip
        if config is None:
            config = str(ours) if (ours := config_file(algo, env_id)) else None
        elif not Path(config).exists() and (ours := hyperparams_dir() / Path(config).name).is_file():
            config = str(ours)
        super().__init__(args, algo, env_id, *more, config=config, **kwargs)
        self.run_folder: Path | None = None

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        hyperparams, saved_hyperparams = super().read_hyperparameters()
        for key, (option, default) in OPTIONS.items():
            value = hyperparams.pop(key, None)
            if value is not None and getattr(self, key) == default and not given_on_command_line(option):
                setattr(self, key, int(value))
        if hyperparams.get("env_kwargs"):  # the zoo gives them to the training env only: evaluate and record in it
            if getattr(self.args, "eval_env_kwargs", None) is None:
                self.eval_env_kwargs = hyperparams["env_kwargs"]
            if getattr(self.args, "env_kwargs", None) is None:
                self.args.env_kwargs = hyperparams["env_kwargs"]  # args.yml, where record_video reads them
        errors.read_schedules(hyperparams)
        return hyperparams, saved_hyperparams

    def create_log_folder(self) -> None:
        # The zoo numbers a run as it starts and makes its folder with exist_ok: two runs started together would write
        # into one. os.mkdir fails for the later, which takes the next number.
        os.makedirs(self.log_path, exist_ok=True)
        while True:
            try:
                os.mkdir(self.save_path)
                break
            except FileExistsError:
                number = get_latest_run_id(self.log_path, self.env_name) + 1
                self.save_path = os.path.join(self.log_path, f"{self.env_name}_{number}")
                self.params_path = f"{self.save_path}/{self.env_name}"
        self.run_folder = Path(self.save_path)
        super().create_log_folder()

    def setup_experiment(self) -> Any:
        try:
            if self.continue_training and (problem := saved_model_problem(self.trained_agent)):  # SB3: a traceback
                errors.fail(f"{self.trained_agent} cannot be loaded: {problem}; continue from a checkpoint beside it")
            return super().setup_experiment()
        except BaseException as error:
            self._end_without_model(error)
            raise

    def learn(self, model: Any) -> None:
        if getattr(model, "online_fraction", None) is not None:  # an online fine-tuning: its transitions are data
            for callback in self.callbacks:
                if isinstance(callback, CheckpointCallback):
                    callback.save_replay_buffer = True
            agent = Path(self.trained_agent)  # -i rl_model_<N>_steps.zip: with its transitions, unless the zoo loads any
            step = agent.name.removeprefix("rl_model_").removesuffix("_steps.zip")
            buffer, zoos = agent.with_name(f"rl_model_replay_buffer_{step}_steps.pkl"), agent.with_name("replay_buffer.pkl")
            if self.continue_training and step.isdigit() and buffer.is_file() and not zoos.is_file():
                print(f"Loading the replay buffer of the checkpoint: {buffer}")
                model.load_replay_buffer(buffer)
        start = model.num_timesteps
        with interrupts_noted() as noted:
            try:
                super().learn(model)  # which saves the model at Ctrl-C
            except Exception as error:  # a fine-tuning loads its offline data here
                self._end_without_model(error)
                raise
        if noted() == signal.SIGINT and model.num_timesteps == start:  # before the first step: no model to save
            self._end_without_model(KeyboardInterrupt())

    def save_trained_model(self, model: Any) -> None:
        try:
            super().save_trained_model(model)
        except OSError as error:  # a full disk: the save leaves the file before it (atomic saves), and one line
            self._end_without_model(error)
            raise

    def _end_without_model(self, error: BaseException) -> None:
        """Remove the run's folder if it holds no model; end on one line for Ctrl-C (130) or an input error (2)."""
        folder = self.run_folder
        if removed := folder is not None and folder.is_dir() and not any(folder.rglob("*.zip")):
            shutil.rmtree(folder, ignore_errors=True)
        if isinstance(error, KeyboardInterrupt):
            if not getattr(error, "said", False):  # a dataset's collection says what it kept
                print(f"interrupted before training started: no model saved{f', {folder} removed' if removed else ''}",
                      file=sys.stderr)  # fmt: skip
            raise SystemExit(INTERRUPTED_STATUS) from None
        if isinstance(error, (*errors.INPUT_ERRORS, OSError)):  # OSError: a disk without room, a read-only folder
            errors.fail(os_error_line(error, folder, "-f") if isinstance(error, OSError) else str(error))


#: Our algorithms by ``--algo`` name.
ALGOS = {"cql": CQL, "calql": CalQL, "bc": BC, "iql": IQL}
#: Our Optuna samplers for ``-optimize`` by ``--algo`` name (a study's trial read back with ``convert_params``).
SEARCH_SPACES = {"cql": search_space.sample_cql_params, "calql": search_space.sample_cql_params,
                 "iql": search_space.sample_iql_params}  # fmt: skip


def register() -> None:
    """Add our part to the zoo's modules (once: again changes nothing)."""
    for name, algorithm in ALGOS.items():
        utils.ALGOS.setdefault(name, algorithm)
    for name, algorithm in utils.ALGOS.items():  # a kill during a save leaves the file before it, not a part
        if not getattr(algorithm, "saves_atomically", False):
            utils.ALGOS[name] = with_atomic_saves(algorithm)
    for name, sampler in SEARCH_SPACES.items():
        hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault(name, sampler)
        hyperparams_opt.HYPERPARAMS_CONVERTER.setdefault(name, search_space.convert_params)
    for module in (exp_manager, sys.modules.get("rl_zoo3.train")):  # train.py imports the name
        if module is not None:
            module.ExperimentManager = ExperimentManager
    if not hasattr(utils.StoreDict.__call__, "__wrapped__"):
        utils.StoreDict.__call__ = errors.store_dict_call(utils.StoreDict.__call__)


register()
