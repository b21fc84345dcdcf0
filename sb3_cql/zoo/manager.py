"""What the zoo's ``ExperimentManager`` lacks, added by wrapping the public methods named in
:data:`~sb3_cql.zoo.internals.ZOO_INTERNALS`: each calls the zoo's own and then the module named for the behaviour."""

from __future__ import annotations

import functools
import inspect
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any

from rl_zoo3 import utils as zoo_utils

from sb3_cql.zoo import checkpoints, errors, pretrained, run_end, run_folders
from sb3_cql.zoo.chunked import apply_chunked_entry
from sb3_cql.zoo.eval_freq import apply_config_options
from sb3_cql.zoo.internals import ZOO_INTERNALS, zoo_internal
from sb3_cql.zoo.noise import apply_action_noise, read_noise_settings
from sb3_cql.zoo.registry import ALGOS, config_file, our_config


def wrap_problems(manager: type) -> list[str]:
    """What of the :data:`ZOO_INTERNALS` methods ``manager`` lacks: a method, or a parameter the plugin binds."""
    problems = []
    for internal in ZOO_INTERNALS:
        if internal.kind != "method":
            continue
        method = getattr(manager, internal.name.rsplit(".", 1)[-1], None)
        if not callable(method):
            problems.append(f"no {internal.name}")
            continue
        missing = [name for name in internal.uses if name not in inspect.signature(method).parameters]
        problems += [f"{internal.name} has no parameter {name!r}" for name in missing]
    return problems


def extend_exp_manager(exp_manager: ModuleType) -> None:
    """Wrap the :data:`ZOO_INTERNALS` methods of ``exp_manager.ExperimentManager`` (all of them or, where the zoo lacks
    one, none, with a warning), and make train.py's ``KEY:VALUE`` items that do not evaluate one line."""
    if not getattr(zoo_utils.StoreDict.__call__, "_sb3_cql_wrapped", False):
        zoo_utils.StoreDict.__call__ = errors.store_dict_call(zoo_utils.StoreDict)
    manager = exp_manager.ExperimentManager
    problems = wrap_problems(manager)
    if problems:
        warnings.warn(f"sb3-cql's zoo plugin does not fit this rl_zoo3 ({'; '.join(problems)}): its configs, evaluation "
                      "settings and messages are off", RuntimeWarning, stacklevel=2)  # fmt: skip
        return
    zoo = {internal.name.rsplit(".", 1)[-1]: getattr(manager, internal.name.rsplit(".", 1)[-1])
           for internal in ZOO_INTERNALS if internal.kind == "method"}  # fmt: skip
    config_parameter, eval_env_kwargs_parameter = zoo_internal("ExperimentManager.__init__").uses
    (eval_env_parameter,) = zoo_internal("ExperimentManager.create_envs").uses
    init_signature, create_envs_signature = inspect.signature(zoo["__init__"]), inspect.signature(zoo["create_envs"])

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        zoo["__init__"](self, *args, **kwargs)
        given = init_signature.bind(self, *args, **kwargs).arguments
        self._sb3_cql_eval_env_kwargs_given = given.get(eval_env_kwargs_parameter) is not None
        if given.get(config_parameter) is not None:
            self.config = our_config(self.config)
        elif (ours := config_file(self.algo, self.env_name.gym_id)) is not None:
            self.config = str(ours)

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        hyperparams, saved_hyperparams = zoo["read_hyperparameters"](self)
        if self.algo in ALGOS:
            apply_chunked_entry(self, hyperparams, saved_hyperparams)
        apply_config_options(self, hyperparams)
        if "env_kwargs" in hyperparams:
            if not getattr(self, "_sb3_cql_eval_env_kwargs_given", False):
                # The zoo gives a config's env_kwargs to the training env only: evaluate in the env trained in.
                self.eval_env_kwargs = hyperparams["env_kwargs"]
            if hyperparams["env_kwargs"] and getattr(self.args, "env_kwargs", None) is None:
                self.args.env_kwargs = hyperparams["env_kwargs"]  # args.yml, where record_video reads them
        if self.algo in ALGOS:
            read_noise_settings(self, hyperparams)
            errors.check_hyperparameters(zoo_utils.ALGOS[self.algo], hyperparams)
            errors.read_schedules(hyperparams)
        return hyperparams, saved_hyperparams

    def setup_experiment(self) -> Any:
        try:
            if self.continue_training and (damaged := checkpoints.damaged_model(Path(self.trained_agent))) is not None:
                errors.fail(damaged)  # SB3's load would fail with a traceback
            result = zoo["setup_experiment"](self)
            if result is not None:
                checkpoints.atomic_saves(result[0])
                if self.algo in ALGOS:
                    apply_action_noise(self, result[0])
            return result
        except BaseException as error:
            # The zoo makes the run's folder before the model, whose dataset may first be collected: a run stopped
            # there leaves no folder, and the next run takes its number.
            removed = run_folders.remove_model_less_folder(getattr(self, "_sb3_cql_run_folder", None))
            if isinstance(error, KeyboardInterrupt):
                if getattr(error, "said", False):  # a dataset collection says what it kept itself
                    raise SystemExit(run_end.INTERRUPTED_STATUS) from None
                run_end.interrupted_before_training(removed, "no model yet")
            if errors.input_error(error):
                errors.fail(str(error))
            raise

    def create_log_folder(self) -> None:
        self._sb3_cql_run_folder = run_folders.claim_run_folder(self)
        zoo["create_log_folder"](self)

    def create_envs(self, *args: Any, **kwargs: Any) -> Any:
        env = zoo["create_envs"](self, *args, **kwargs)
        call = create_envs_signature.bind(self, *args, **kwargs)
        call.apply_defaults()
        if self.continue_training and not call.arguments[eval_env_parameter]:
            if not hasattr(self, "_sb3_cql_saved_spaces"):
                self._sb3_cql_saved_spaces = pretrained.saved_spaces(self.trained_agent)
            misfit = pretrained.misfit(self._sb3_cql_saved_spaces, env)
            if misfit is not None:  # another action mode: SB3's load would raise with a traceback
                env.close()
                env_kwargs = f" {self.env_kwargs}" if self.env_kwargs else ""
                errors.fail(f"{self.trained_agent} does not fit {self.env_name.gym_id}{env_kwargs}: {misfit}")
        return env

    def learn(self, model: Any) -> None:
        checkpoints.keep_transitions(self.callbacks, model, self.trained_agent if self.continue_training else None)
        self._sb3_cql_start_step = getattr(model, "num_timesteps", None)
        try:
            with run_end.ctrl_c_noted(self):
                zoo["learn"](self, model)
        except Exception as error:  # a fine-tuning loads its offline data here
            if not errors.input_error(error):
                raise
            run_folders.remove_model_less_folder(getattr(self, "_sb3_cql_run_folder", None))
            errors.fail(str(error))

    def save_trained_model(self, model: Any) -> None:
        interrupted = getattr(self, "_sb3_cql_interrupted", False)
        if interrupted and getattr(model, "num_timesteps", None) == getattr(self, "_sb3_cql_start_step", -1):
            # Ctrl-C before the first step (while the data were loaded or collected): no model to keep.
            removed = run_folders.remove_model_less_folder(getattr(self, "_sb3_cql_run_folder", None))
            run_end.interrupted_before_training(removed, "no model saved")
        zoo["save_trained_model"](self, model)
        if self.algo in ALGOS:
            run_end.say_how_it_ended(self, model)

    ours = {wrapper.__name__: wrapper for wrapper in (__init__, read_hyperparameters, setup_experiment, create_log_folder,
                                                      create_envs, learn, save_trained_model)}  # fmt: skip
    assert set(ours) == set(zoo), "every wrapped method is named in ZOO_INTERNALS"
    for name, wrapper in ours.items():
        setattr(manager, name, functools.wraps(zoo[name])(wrapper))
