"""What the package adds to RL-Zoo3: ``cql``, ``bc`` and ``iql`` in ``ALGOS``, the Panda tasks, the CQL and IQL
search spaces, and our ``hyperparams/`` files as the default config of our algorithms and tasks.

:func:`extend` is called by :mod:`sb3_cql.zoo.hook` right after each zoo module in ``hook.TRIGGERS`` is imported;
``import sb3_cql.zoo.plugin`` extends whichever of them are already loaded and installs the hook for the others.
It wraps public ``ExperimentManager`` methods only; :data:`ZOO_INTERNALS` names every part of the zoo (and of SB3)
it relies on beyond their documented use.
"""

from __future__ import annotations

import argparse
import functools
import inspect
import os
import re
import shlex
import shutil
import signal
import sys
import threading
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple, NoReturn

#: The algorithm the package adds to the zoo, with its search space.
ALGO = "cql"
#: Every algorithm the package adds: our config file is their default config on any env.
ALGOS = (ALGO, "bc", "iql")
#: ``train.py``'s defaults of ``--eval-freq`` and ``--eval-episodes``: a config's ``eval_freq`` / ``n_eval_episodes``
#: replace them; a value given on the command line (or any other value) wins over the config.
ZOO_DEFAULT_EVAL_FREQ, ZOO_DEFAULT_EVAL_EPISODES = 25_000, 5
#: ``train.py``'s default of ``--save-freq`` (no checkpoints): a config's ``save_freq`` replaces it.
ZOO_DEFAULT_SAVE_FREQ = -1


class ZooInternal(NamedTuple):
    """A part of RL-Zoo3 (or SB3) the plugin relies on that a new version could change without notice.

    :param kind: ``"method"``: an ``ExperimentManager`` method the plugin wraps, ``uses`` the parameters it binds by
        name; ``"attribute"``: an attribute the plugin reads or sets, ``uses`` what of it; ``"option"``: an option
        of ``rl_zoo3.train``, ``uses`` its default and the ``ExperimentManager`` attribute it sets (for ours also the
        config key that replaces it); ``"behaviour"``: something the zoo's or SB3's code does that the plugin builds on.
    :param name: where it is.
    :param uses: what of it the plugin uses.
    :param reason: why the plugin needs it.
    """

    kind: str
    name: str
    uses: tuple[Any, ...]
    reason: str


#: Everything of RL-Zoo3 and SB3 the plugin relies on beyond their documented use, each checked against the installed
#: versions by ``tests/test_zoo_internals.py``. The plugin wraps public methods only and matches no error text.
ZOO_INTERNALS: tuple[ZooInternal, ...] = (
    ZooInternal("method", "ExperimentManager.__init__", ("config", "eval_env_kwargs"),
                "our hyperparams/ file unless --conf-file is given; whether --eval-env-kwargs was given"),
    ZooInternal("method", "ExperimentManager.read_hyperparameters", (),
                "returns (hyperparams, saved copy): our config keys out of the first; its env_kwargs for evaluation too; "
                "a chunked -i model's settings in; our noise keys out"),
    ZooInternal("method", "ExperimentManager.setup_experiment", (),
                "a damaged -i model, a dataset error or a bad setting ends the run on one line; a run stopped before its "
                "first model (e.g. while its dataset is collected) leaves no folder; returns (model, saved "
                "hyperparams), whose model gets our action noise and saves that leave a file whole or none"),
    ZooInternal("method", "ExperimentManager.create_log_folder", (),
                "the run's folder claimed with os.mkdir: two runs started at once take two numbers"),
    ZooInternal("method", "ExperimentManager.create_envs", ("eval_env",),
                "an -i model whose spaces do not fit the training env ends the run on one line, before SB3 loads it"),
    ZooInternal("method", "ExperimentManager.learn", ("model",),
                "Ctrl-C noted (the zoo swallows it); fine-tuning checkpoints keep, and -i CHECKPOINT loads, transitions; "
                "a dataset error or a bad setting ends the run on one line"),
    ZooInternal("method", "ExperimentManager.save_trained_model", ("model",),
                "where the models are and how to use them, or what an interrupted run kept"),
    ZooInternal("attribute", "rl_zoo3.utils.ALGOS", ALGOS, "--algo's choices and the classes the zoo builds"),
    ZooInternal("attribute", "rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER", (ALGO, "iql"),
                "CQL's and IQL's search spaces for -optimize"),
    ZooInternal("attribute", "rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER", (ALGO, "iql"),
                "a study's trial as CQL or IQL keywords"),
    ZooInternal("attribute", "ExperimentManager.algo", ("read",), "our config and messages for our algorithms only"),
    ZooInternal("attribute", "ExperimentManager.env_name", ("gym_id",), "the env id of our config, commands and messages"),
    ZooInternal("attribute", "ExperimentManager.config", ("read", "set"), "the config file read_hyperparameters loads"),
    ZooInternal("attribute", "ExperimentManager.env_kwargs", ("read",), "the training env's kwargs, named when -i misfits"),
    ZooInternal("attribute", "ExperimentManager.eval_env_kwargs", ("set",), "the kwargs create_envs gives the evaluation env"),
    ZooInternal("attribute", "ExperimentManager.args", ("env_kwargs",), "the train.py Namespace the zoo saves as args.yml"),
    ZooInternal("attribute", "ExperimentManager.callbacks", ("read",), "the CheckpointCallback the zoo made for --save-freq"),
    ZooInternal("attribute", "ExperimentManager.save_path", ("read", "set"),
                "the run's folder, moved to the next free number when another run made it first"),
    ZooInternal("attribute", "ExperimentManager.params_path", ("set",), "<save_path>/<env id>, moved with the run's folder"),
    ZooInternal("attribute", "ExperimentManager.log_path", ("read",), "<log folder>/<algo>/, where the run folders are"),
    ZooInternal("attribute", "ExperimentManager.trained_agent", ("read",), "the -i model"),
    ZooInternal("attribute", "ExperimentManager.continue_training", ("read",), "whether -i names a model to load"),
    ZooInternal("attribute", "ExperimentManager.n_timesteps", ("read",), "the step count an interrupted run names"),
    ZooInternal("attribute", "ExperimentManager.custom_hyperparams", ("read",),
                "the --hyperparams values, which a config's chunked entry does not override"),
    ZooInternal("attribute", "ExperimentManager.seed", ("read",), "the run's seed, which seeds the pink noise"),
    ZooInternal("option", "--eval-freq", (ZOO_DEFAULT_EVAL_FREQ, "eval_freq"), "a config's eval_freq replaces the default"),
    ZooInternal("option", "--eval-episodes", (ZOO_DEFAULT_EVAL_EPISODES, "n_eval_episodes"),
                "a config's n_eval_episodes replaces the default"),
    ZooInternal("option", "--save-freq", (ZOO_DEFAULT_SAVE_FREQ, "save_freq"), "a config's save_freq replaces the default"),
    ZooInternal("option", "--env-kwargs", (None, "env_kwargs"), "None when not given: the config's go to args.yml then"),
    ZooInternal("behaviour", "train.py reads --hyperparams and --env-kwargs with utils.StoreDict, which evals each VALUE",
                (), "a VALUE that does not evaluate is one line saying what to type (StoreDict.__call__ wrapped)"),
    ZooInternal("behaviour", "enjoy.py and record_video.py find the model they load with utils.get_model_path", (),
                "a damaged model is one line naming the last good checkpoint (get_model_path wrapped)"),
    ZooInternal("behaviour", "train.train parses sys.argv[1:]",
                (), "the only record of which options were given: the Namespace holds values, the parser is local"),
    ZooInternal("behaviour", "train.train calls learn, then save_trained_model", (),
                "how a run ended is said after the zoo's save"),
    ZooInternal("behaviour", "ExperimentManager.learn returns after Ctrl-C", (),
                "the zoo catches KeyboardInterrupt to save the model: the plugin only notes that it came"),
    ZooInternal("behaviour", "ExperimentManager.learn trains with self.callbacks", (),
                "the CheckpointCallback set to keep the replay buffer is the one that runs"),
    ZooInternal("behaviour", "ExperimentManager.create_callbacks checkpoints as rl_model in save_path", (),
                "a checkpoint's transitions are found beside it by SB3's names for that prefix"),
    ZooInternal("behaviour", "CheckpointCallback saves <prefix>_replay_buffer_<N>_steps.pkl", (),
                "the name -i CHECKPOINT looks for"),
    ZooInternal("behaviour", "ExperimentManager._load_pretrained_agent loads replay_buffer.pkl beside the model", (),
                "a checkpoint's own transitions are loaded only where the zoo loads none"),
    ZooInternal("behaviour", "ExperimentManager.setup_experiment loads -i with the env of create_envs(eval_env=False)", (),
                "that env is the one whose spaces the plugin checks"),
    ZooInternal("behaviour", "BaseAlgorithm.load checks spaces with check_for_correct_spaces", (),
                "the plugin's check of an -i model is SB3's own, made before the load"),
    ZooInternal("behaviour", "ExperimentManager._preprocess_hyperparams takes env_kwargs from read_hyperparameters", (),
                "the evaluation env gets the kwargs the training env gets"),
    ZooInternal("behaviour", "ExperimentManager._save_config writes args as args.yml, where record_video reads env_kwargs",
                (), "a run's videos are recorded in the action mode it was trained in"),
    ZooInternal("behaviour", "ExperimentManager.save_path is <log folder>/<algo>/<env id>_<N>", (),
                "the log folder and --exp-id of the commands printed at the end"),
    ZooInternal("behaviour", "ExperimentManager.setup_experiment uses save_path and params_path first in create_log_folder",
                (), "a folder claimed there is the one the run's callbacks, monitor, config and models are written in"),
    ZooInternal("behaviour", "the zoo saves the model it trains with model.save and model.save_replay_buffer", (),
                "CheckpointCallback, EvalCallback's best_model and save_trained_model write through the model's class, "
                "which the plugin gives saves that leave a file whole or none"),
    ZooInternal("behaviour", "ExperimentManager.read_hyperparameters applies --hyperparams before returning", (),
                "a chunked entry's settings are added after them, without overriding them"),
    ZooInternal("behaviour", "ExperimentManager._preprocess_action_noise knows normal and ornstein-uhlenbeck only", (),
                "noise_type pink and noise_hold are taken out of the hyperparameters before it runs"),
    ZooInternal("behaviour", "ExperimentManager.objective calls the sampler with (trial, n_actions, n_envs, additional_args)",
                (), "sample_cql_params's signature"),
)  # fmt: skip

#: The ``rl_zoo3.train`` options a config key replaces while the option is at its default: the key is the name of the
#: ``ExperimentManager`` attribute the option sets (:data:`ZOO_INTERNALS` has the defaults).
CONFIG_OPTIONS = ("--eval-freq", "--eval-episodes", "--save-freq")
#: A config key of ours: settings that apply when the ``-i`` model acts in action chunks (``cql_finetune.yml``).
CHUNKED_KEY = "chunked"
#: Steps of a pink-noise sequence on an env without a time limit.
PINK_SEQ_LEN = 1000
#: ``rl_zoo3.train``'s name in its error lines.
PROG = "python -m rl_zoo3.train"
#: Our errors that say what to fix in the command line, the config or the data, as ``(module, class)``: a run ends
#: on their one line (any other error is a bug, shown with its traceback).
INPUT_ERRORS = (
    ("sb3_cql.data.replay", "DatasetError"),
    ("sb3_cql.common.offline", "SettingError"),
    ("sb3_cql.cql.cql", "TrainingDivergedError"),
    ("envs.config", "ConfigError"),
)
#: The keys of a config (and of ``--hyperparams``) that the zoo takes out before it makes the model: with the
#: keywords of the algorithm's class, the keys it takes.
ZOO_KEYS = ("n_timesteps", "n_envs", "normalize", "env_wrapper", "vec_env_wrapper", "frame_stack", "callback",
            "monitor_kwargs", "env_kwargs", "noise_type", "noise_std")  # fmt: skip
#: The hyperparameters whose string values the zoo reads as schedules, ``lin_<initial value>``.
SCHEDULE_KEYS = ("learning_rate",)


def zoo_internal(name: str) -> ZooInternal:
    """The entry of :data:`ZOO_INTERNALS` named ``name``."""
    for internal in ZOO_INTERNALS:
        if internal.name == name:
            return internal
    raise KeyError(f"{name!r} is not in ZOO_INTERNALS")


def hyperparams_dir() -> Path:
    """Our zoo config files: ``hyperparams/`` of the source tree (editable installs), else the installed copy."""
    source_tree, installed = Path(__file__).resolve().parents[2], Path(sys.prefix) / "share" / "sb3-cql"
    for folder in (source_tree / "hyperparams", installed / "hyperparams"):
        if (folder / f"{ALGO}.yml").is_file():
            return folder
    raise FileNotFoundError("sb3-cql's hyperparams/ folder is missing: reinstall the package")


def config_file(algo: str, env_id: str) -> Path | None:
    """Our config for ``algo`` on ``env_id``: always for our algorithms, for others when our file has the env."""
    import yaml

    path = hyperparams_dir() / f"{algo}.yml"
    if not path.is_file():
        return None
    if algo in ALGOS:
        return path
    with open(path) as file:
        return path if env_id in (yaml.safe_load(file) or {}) else None


def extend(module: ModuleType) -> None:
    """Add our part to the zoo module ``module`` (once; other modules are left alone)."""
    extension = _EXTENSIONS.get(module.__name__)
    if extension is not None and not getattr(module, "_sb3_cql_extended", False):
        extension(module)
        module._sb3_cql_extended = True  # type: ignore[attr-defined]


def _extend_utils(utils: ModuleType) -> None:
    import envs  # noqa: F401  (registers the tasks' gymnasium ids)
    from sb3_cql.bc import BC
    from sb3_cql.cql import CQL
    from sb3_cql.iql import IQL

    utils.ALGOS.setdefault(ALGO, CQL)
    utils.ALGOS.setdefault("bc", BC)
    utils.ALGOS.setdefault("iql", IQL)
    if not getattr(utils.get_model_path, "_sb3_cql_wrapped", False):  # enjoy.py and record_video.py import it after
        utils.get_model_path = _checked_model_path(utils.get_model_path)


def _checked_model_path(get_model_path: Any) -> Any:
    """The zoo's ``get_model_path`` (the model that enjoy.py and record_video.py load), ending the command on one line
    where the model cannot be loaded (a copy or a save cut short), naming the newest checkpoint beside it that opens."""

    @functools.wraps(get_model_path)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        found = get_model_path(*args, **kwargs)
        damaged = _damaged_model(Path(found[1]))
        if damaged is not None:
            print(f"python -m rl_zoo3.{Path(sys.argv[0]).stem}: error: {damaged}", file=sys.stderr)
            raise SystemExit(2)
        return found

    wrapper._sb3_cql_wrapped = True  # type: ignore[attr-defined]
    return wrapper


def _extend_hyperparams_opt(hyperparams_opt: ModuleType) -> None:
    from sb3_cql.zoo.search_space import convert_cql_params, convert_iql_params, sample_cql_params, sample_iql_params

    hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault(ALGO, sample_cql_params)
    hyperparams_opt.HYPERPARAMS_CONVERTER.setdefault(ALGO, convert_cql_params)
    hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault("iql", sample_iql_params)
    hyperparams_opt.HYPERPARAMS_CONVERTER.setdefault("iql", convert_iql_params)


def _given_on_command_line(option: str, argv: list[str] | None = None) -> bool:
    """Whether ``rl_zoo3.train``'s ``option`` is in ``argv`` (default ``sys.argv[1:]``, what train.py parses), spelt
    any way argparse takes it: ``--eval-freq 5``, ``--eval-freq=5`` or an abbreviation (``--eval-fr 5``).

    The command line is the only record: the zoo's Namespace holds values (``--eval-episodes 5`` is the default's
    value, yet the user's choice) and its parser is local to ``train()``. A parser of this one option, with argparse's
    own rules, reads it as the zoo's did: an abbreviation the zoo took is one of this option's prefixes.
    """
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument(option, dest="given", nargs="?", default=argparse.SUPPRESS)
    try:
        known, _ = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    except argparse.ArgumentError:  # the option is there, in a form a parser of it alone rejects
        return True
    return hasattr(known, "given")


def _left_at_default(option: str, value: Any) -> bool:
    """Whether the zoo's ``option`` has train.py's default ``value`` and was not given on the command line (where a
    value equal to the default is still the user's choice)."""
    default, _ = zoo_internal(option).uses
    return value == default and not _given_on_command_line(option)


def _our_config(config: str) -> str:
    """``config`` (``--conf-file``), or where it names one of our files that is not there (``cql_finetune.yml``
    outside the source tree), our installed copy of it."""
    ours = hyperparams_dir() / Path(config).name
    return str(ours) if not Path(config).exists() and ours.is_file() else config


def _checkpoint_parts(model_path: Path) -> tuple[str, int] | None:
    """The prefix and step of a checkpoint ``<prefix>_<N>_steps.zip`` (SB3's ``CheckpointCallback``), else None."""
    parts = model_path.stem.rsplit("_", 2)  # rl_model, <N>, steps
    if len(parts) != 3 or parts[2] != "steps" or not parts[1].isdigit():
        return None
    return parts[0], int(parts[1])


def _checkpoint_buffer(model_path: Path) -> Path | None:
    """The replay buffer saved with a checkpoint ``rl_model_<N>_steps.zip`` (SB3's ``CheckpointCallback``), if any."""
    parts = _checkpoint_parts(model_path)
    if parts is None:
        return None
    path = model_path.with_name(f"{parts[0]}_replay_buffer_{parts[1]}_steps.pkl")
    return path if path.is_file() else None


def _damaged_model(model_path: Path) -> str | None:
    """Why the ``-i`` model at ``model_path`` cannot be loaded (a copy or a save cut short), naming the newest checkpoint
    beside it that opens, the one to continue from; None where it opens."""
    from sb3_cql.common.atomic import saved_model_problem

    problem = saved_model_problem(model_path)
    if problem is None:
        return None
    checkpoints = sorted(((parts[1], path) for path in model_path.parent.glob("rl_model_*_steps.zip")
                          if path != model_path and (parts := _checkpoint_parts(path)) is not None), reverse=True)  # fmt: skip
    good = next((path for _, path in checkpoints if saved_model_problem(path) is None), None)
    beside = f"the last good checkpoint beside it is {good}" if good else "no checkpoint beside it opens"
    return f"{model_path} cannot be loaded: {problem}; {beside}"


def _holds_a_model(folder: Path) -> bool:
    """Whether a zoo run folder holds a saved model (any ``.zip``): a run that got as far as its first checkpoint."""
    return any(folder.rglob("*.zip"))


def _claim_run_folder(manager: Any) -> Path:
    """Make the run's folder, ``save_path``, with ``os.mkdir``, which fails where it exists: a run started at the same
    moment (which took the same number in ``__init__``) made it first, and this one takes the next free number, with
    ``save_path`` and ``params_path`` moved there."""
    folder = Path(manager.save_path)
    folder.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            folder.mkdir()
            return folder
        except FileExistsError:
            numbered = re.fullmatch(rf"{re.escape(str(manager.env_name))}_(\d+)(.*)", folder.name)
            if numbered is None:
                raise
            manager.save_path = os.path.join(manager.log_path, f"{manager.env_name}_{int(numbered[1]) + 1}{numbered[2]}")
            manager.params_path = f"{manager.save_path}/{manager.env_name}"
            folder = Path(manager.save_path)


def _remove_model_less_folder(manager: Any) -> Path | None:
    """Remove the run folder this run made if it holds no model yet (the next run takes its number); return it then."""
    folder = getattr(manager, "_sb3_cql_run_folder", None)
    if folder is None or not folder.is_dir() or _holds_a_model(folder):
        return None
    shutil.rmtree(folder, ignore_errors=True)
    return folder


def _input_error(error: BaseException) -> bool:
    """Whether ``error`` is one of :data:`INPUT_ERRORS`, looked up in the modules loaded: a run that never loaded a
    dataset cannot have a ``DatasetError``, and imports no Minari to check it."""
    return any(isinstance(error, getattr(sys.modules[module], name)) for module, name in INPUT_ERRORS if module in sys.modules)


def _fail(message: str) -> NoReturn:
    """End the run on one line, ``python -m rl_zoo3.train: error: ...``, with status 2 (a usage error's)."""
    print(f"{PROG}: error: {' '.join(message.split())}", file=sys.stderr)
    raise SystemExit(2) from None


def zoo_parse_error(
    option: str, item: str, problem: BaseException | str, hint: str | None = None, prog: str = PROG
) -> NoReturn:
    """End a zoo command on one line for a ``KEY:VALUE`` item of ``option`` (``--hyperparams``, ``--env-kwargs``) that
    the zoo cannot read (it evaluates VALUE as Python): what is wrong, and ``hint`` or what to type instead; status 2.
    The one place the zoo's parse errors become a line."""
    key, _, value = item.partition(":")
    why = f"{type(problem).__name__}: {problem}" if isinstance(problem, BaseException) else problem
    if hint is None:
        hint = (f"write KEY:VALUE with a Python value: a number as it is (batch_size:64), a string in quotes "
                f"inside the shell's ({key or 'KEY'}:\"'{value}'\")")  # fmt: skip
    print(f"{prog}: error: {option} {item}: {' '.join(why.split())}; {hint}", file=sys.stderr)
    raise SystemExit(2)


def _store_dict_call(store_dict: type) -> Any:
    """The zoo's ``StoreDict.__call__`` (``KEY:VALUE`` items, VALUE evaluated as Python) with a value that does not
    evaluate, or an item without a key, ending the command on :func:`zoo_parse_error`'s line."""
    call = store_dict.__call__

    @functools.wraps(call)
    def __call__(self: Any, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        prog = f"python -m rl_zoo3.{Path(parser.prog).stem}"
        for item in values:
            key, separator, value = item.partition(":")
            if not key or not separator:
                zoo_parse_error(option_string, item, "not KEY:VALUE", prog=prog)
            try:
                eval(value)  # as the zoo does next
            except Exception as error:
                zoo_parse_error(option_string, item, error, prog=prog)
        call(self, parser, namespace, values, option_string)

    __call__._sb3_cql_wrapped = True  # type: ignore[attr-defined]
    return __call__


def _check_hyperparameters(algo: type, hyperparams: dict[str, Any]) -> None:
    """Before the zoo reads them: a key that neither the zoo nor ``algo`` takes is a
    :class:`~sb3_cql.common.offline.KeywordError` naming the closest one; a schedule that is neither a number nor
    ``lin_<initial value>`` is :func:`zoo_parse_error`'s line."""
    refuse = getattr(algo, "refuse_unknown_keywords", None)
    if refuse is not None:
        refuse([key for key in hyperparams if key not in ZOO_KEYS])
    for key in SCHEDULE_KEYS:
        value = hyperparams.get(key)
        if isinstance(value, str):
            schedule, _, initial = value.partition("_")
            try:
                valid = schedule == "lin" and float(initial) > 0
            except ValueError:
                valid = False
            if not valid:
                zoo_parse_error("--hyperparams", f"{key}:{value!r}", f"{key} must be a number >= 0 or a linear schedule "
                                f"'lin_<initial value>'", f"e.g. {key}:0.0003 or {key}:\"'lin_0.0003'\"")  # fmt: skip


def _atomic_saves(model: Any) -> None:
    """Make the saves of ``model`` (one of SB3's or another library's algorithms) leave a file whole or none, as ours
    do: its class becomes :func:`~sb3_cql.common.atomic.with_atomic_saves` of it, its behaviour otherwise the same."""
    from stable_baselines3.common.base_class import BaseAlgorithm

    from sb3_cql.common.atomic import with_atomic_saves

    if isinstance(model, BaseAlgorithm) and not getattr(type(model), "saves_atomically", False):
        model.__class__ = with_atomic_saves(type(model))


def _run_commands(algo: str, env_id: str, save_path: Path) -> list[str]:
    """What to do with a run's models: evaluate on the three tasks, record a video (the zoo's own ``--exp-id``), each
    command quoted for the shell (a folder with a space is one word)."""
    log_folder, exp_id = save_path.parent.parent, save_path.name.rsplit("_", 1)[-1]
    model = save_path / ("best_model.zip" if (save_path / "best_model.zip").is_file() else f"{env_id}.zip")
    load_best = ["--load-best"] if model.name == "best_model.zip" else []
    evaluate = ["python", "-m", "sb3_cql.evaluate", str(model), "--algo", algo, "-n", "100"]
    record = ["python", "-m", "rl_zoo3.record_video", "--algo", algo, "--env", env_id, "-f", str(log_folder),
              "--exp-id", exp_id, *load_best, "-n", "700"]  # fmt: skip
    return [f"evaluate on the three tasks: {shlex.join(evaluate)}", f"record a video: {shlex.join(record)}"]


def _saved_data(model_path: str) -> dict[str, Any]:
    """The attributes saved in the SB3 model ``model_path`` (its ``data``: spaces, ``action_chunk``, ...)."""
    from stable_baselines3.common.save_util import load_from_zip_file

    data, _, _ = load_from_zip_file(model_path, device="cpu", load_data=True)
    return data or {}


def _saved_spaces(model_path: str) -> tuple[Any, Any] | None:
    """The observation and action spaces saved in the SB3 model ``model_path``, if they are gymnasium spaces (SB3
    converts older ones itself when it loads the model)."""
    from gymnasium import spaces

    data = _saved_data(model_path)
    saved = (data.get("observation_space"), data.get("action_space"))
    return saved if all(isinstance(space, spaces.Space) for space in saved) else None


def _apply_chunked_entry(manager: Any, hyperparams: dict[str, Any], saved_hyperparams: dict[str, Any]) -> None:
    """A config's ``chunked`` entry: settings that apply when the ``-i`` model acts in action chunks
    (``action_chunk`` > 1), over the entry's own, below ``--hyperparams``; the key itself leaves both dicts."""
    chunked = hyperparams.pop(CHUNKED_KEY, None)
    saved_hyperparams.pop(CHUNKED_KEY, None)
    if chunked is None:
        return
    if not isinstance(chunked, dict):
        raise SystemExit(f"python -m rl_zoo3.train: error: {manager.config}: '{CHUNKED_KEY}' must be a mapping of "
                         f"settings, got {chunked!r}")  # fmt: skip
    if not manager.continue_training or _saved_data(manager.trained_agent).get("action_chunk", 1) <= 1:
        return
    given = manager.custom_hyperparams or {}
    settings = {key: value for key, value in chunked.items() if key not in given}
    hyperparams.update(settings)
    saved_hyperparams.update(settings)
    print(f"{manager.trained_agent} acts in action chunks: the config's '{CHUNKED_KEY}' settings apply: {settings}")


def _action_noise(manager: Any, model: Any) -> None:
    """Our ``noise_type: pink`` (``pink-noise-rl``'s, seeded by the run's seed) and ``noise_hold`` (each draw held
    for that many steps: :class:`~sb3_cql.common.HeldActionNoise`) as the model's ``action_noise``."""
    from sb3_cql.common.noise import HeldActionNoise, pink_action_noise

    noise_type, noise_std, hold = getattr(manager, "_sb3_cql_noise", (None, None, 1))
    if noise_type == "pink":
        import gymnasium as gym

        seq_len = gym.spec(manager.env_name.gym_id).max_episode_steps or PINK_SEQ_LEN
        model.action_noise = pink_action_noise(float(noise_std), model.action_space.shape[0], seq_len, seed=manager.seed)
        print(f"Applying pink noise with std {noise_std} (sequences of {seq_len} steps)")
    if hold > 1 and model.action_noise is not None:
        model.action_noise = HeldActionNoise(model.action_noise, hold)
        print(f"Each draw of the noise is held for {hold} steps")


def _read_noise_settings(manager: Any, hyperparams: dict[str, Any]) -> None:
    """Take our noise keys out of ``hyperparams`` (the zoo knows ``normal`` and ``ornstein-uhlenbeck`` only, and no
    ``noise_hold``), for :func:`_action_noise` once the model exists."""
    hold = hyperparams.pop("noise_hold", 1)
    if not isinstance(hold, int) or hold < 1:
        raise SystemExit(f"python -m rl_zoo3.train: error: noise_hold must be an integer >= 1, got {hold!r}")
    noise_type, noise_std = None, None
    if str(hyperparams.get("noise_type", "")).strip() == "pink":
        noise_type, noise_std = "pink", hyperparams.pop("noise_std", None)
        del hyperparams["noise_type"]
        if not isinstance(noise_std, (int, float)) or noise_std < 0:
            raise SystemExit(f"python -m rl_zoo3.train: error: noise_type pink needs noise_std >= 0, got {noise_std!r}")
    if hold > 1 and noise_type is None and hyperparams.get("noise_type") is None:
        raise SystemExit("python -m rl_zoo3.train: error: noise_hold holds the draws of a noise_type: give one")
    manager._sb3_cql_noise = (noise_type, noise_std, hold)


def _misfit(saved_spaces: tuple[Any, Any] | None, env: Any) -> str | None:
    """How a model with ``saved_spaces`` does not fit ``env``, by SB3's own check when it loads a model with an env
    (``check_for_correct_spaces``), or None where it fits."""
    from stable_baselines3.common.utils import check_for_correct_spaces

    if saved_spaces is None:
        return None
    try:
        check_for_correct_spaces(env, *saved_spaces)
    except ValueError as error:
        return " ".join(str(error).split())
    return None


def _load_checkpoint_buffer(model: Any, model_path: Path) -> None:
    """Continue an online fine-tuning from a checkpoint with the transitions saved beside it, unless the zoo loaded a
    ``replay_buffer.pkl`` there itself."""
    buffer = _checkpoint_buffer(model_path)
    if buffer is not None and not model_path.with_name("replay_buffer.pkl").is_file():
        print(f"Loading the replay buffer of the checkpoint: {buffer}")
        model.load_replay_buffer(buffer)


def _wrap_problems(manager: type) -> list[str]:
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


def _extend_exp_manager(exp_manager: ModuleType) -> None:
    """Wrap the :data:`ZOO_INTERNALS` methods of ``ExperimentManager``: each calls the zoo's own and adds ours."""
    from rl_zoo3 import utils as zoo_utils
    from stable_baselines3.common.callbacks import CheckpointCallback

    if not getattr(zoo_utils.StoreDict.__call__, "_sb3_cql_wrapped", False):  # train.py's --hyperparams, --env-kwargs
        zoo_utils.StoreDict.__call__ = _store_dict_call(zoo_utils.StoreDict)
    manager = exp_manager.ExperimentManager
    problems = _wrap_problems(manager)
    if problems:
        # The zoo's classes stay as they are: half of the extension would be worse than none.
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
        if given.get(config_parameter) is None:  # no --conf-file
            ours = config_file(self.algo, self.env_name.gym_id)
            if ours is not None:
                self.config = str(ours)
        else:
            self.config = _our_config(self.config)

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        hyperparams, saved_hyperparams = zoo["read_hyperparameters"](self)
        if self.algo in ALGOS:
            _apply_chunked_entry(self, hyperparams, saved_hyperparams)
        # Evaluation and checkpoint settings in a config: the zoo has command-line options for them only. They leave
        # the hyperparameters the model gets, not the saved ones (config.yml records them).
        for option in CONFIG_OPTIONS:
            _, attribute = zoo_internal(option).uses
            value = hyperparams.pop(attribute, None)
            if value is not None and _left_at_default(option, getattr(self, attribute)):
                setattr(self, attribute, int(value))
        if "env_kwargs" in hyperparams:
            if not getattr(self, "_sb3_cql_eval_env_kwargs_given", False):
                # The zoo gives a config's env_kwargs to the training env only (it copied the empty command-line value
                # to the evaluation env before reading the config): evaluate in the env trained in (its action mode).
                self.eval_env_kwargs = hyperparams["env_kwargs"]
            if hyperparams["env_kwargs"] and getattr(self.args, "env_kwargs", None) is None:
                # Recorded in the run's args.yml too: record_video reads env_kwargs from there only, not from config.yml.
                self.args.env_kwargs = hyperparams["env_kwargs"]
        if self.algo in ALGOS:
            _read_noise_settings(self, hyperparams)
            from rl_zoo3.utils import ALGOS as zoo_algos

            _check_hyperparameters(zoo_algos[self.algo], hyperparams)
        return hyperparams, saved_hyperparams

    def setup_experiment(self) -> Any:
        # The zoo makes the run's folder before the model, whose dataset may first be collected: a run stopped there
        # (Ctrl-C, an error) would leave a folder without a model, and shift the next run's number.
        try:
            if self.continue_training:  # a damaged -i model: SB3's load would fail with a traceback
                damaged = _damaged_model(Path(self.trained_agent))
                if damaged is not None:
                    _fail(damaged)
            result = zoo["setup_experiment"](self)
            if result is not None:
                _atomic_saves(result[0])
                if self.algo in ALGOS:
                    _action_noise(self, result[0])
            return result
        except BaseException as error:
            removed = _remove_model_less_folder(self)
            if isinstance(error, KeyboardInterrupt):
                if not getattr(error, "said", False):  # a dataset collection says what it kept itself
                    gone = f", {removed} removed" if removed is not None else ""
                    print(f"interrupted before training started: no model yet{gone}", file=sys.stderr)
                raise SystemExit(130) from None
            if _input_error(error):
                _fail(str(error))
            raise

    def create_log_folder(self) -> None:
        # The zoo numbered the run in __init__ (the highest number there + 1) and makes its folder with exist_ok: two
        # runs started together would both write into one. The first to make it keeps the number.
        self._sb3_cql_run_folder = _claim_run_folder(self)
        zoo["create_log_folder"](self)

    def create_envs(self, *args: Any, **kwargs: Any) -> Any:
        env = zoo["create_envs"](self, *args, **kwargs)
        call = create_envs_signature.bind(self, *args, **kwargs)
        call.apply_defaults()
        if self.continue_training and not call.arguments[eval_env_parameter]:
            # -i MODEL: SB3's load would raise on spaces that do not fit (another action mode) with a traceback.
            if not hasattr(self, "_sb3_cql_saved_spaces"):
                self._sb3_cql_saved_spaces = _saved_spaces(self.trained_agent)
            misfit = _misfit(self._sb3_cql_saved_spaces, env)
            if misfit is not None:
                env.close()
                env_kwargs = f" {self.env_kwargs}" if self.env_kwargs else ""
                _fail(f"{self.trained_agent} does not fit {self.env_name.gym_id}{env_kwargs}: {misfit}")
        return env

    def learn(self, model: Any) -> None:
        if getattr(model, "online_fraction", None) is not None:
            # Online fine-tuning: a checkpoint keeps the online transitions too, to continue from (-i CHECKPOINT).
            for callback in self.callbacks:
                if isinstance(callback, CheckpointCallback):
                    callback.save_replay_buffer = True
            if self.continue_training:
                _load_checkpoint_buffer(model, Path(self.trained_agent))
        # The zoo ends training quietly on Ctrl-C (it catches KeyboardInterrupt) and saves the model: note that it
        # was cut short, to say so after the save.
        self._sb3_cql_interrupted, self._sb3_cql_start_step = False, getattr(model, "num_timesteps", None)

        def note_and_interrupt(signum: int, frame: Any) -> None:
            self._sb3_cql_interrupted = True
            raise KeyboardInterrupt

        main_thread = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, note_and_interrupt) if main_thread else None
        try:
            zoo["learn"](self, model)
        except Exception as error:  # a fine-tuning loads its offline data here
            if not _input_error(error):
                raise
            _remove_model_less_folder(self)
            _fail(str(error))
        finally:
            if main_thread:
                signal.signal(signal.SIGINT, previous)

    def save_trained_model(self, model: Any) -> None:
        interrupted = getattr(self, "_sb3_cql_interrupted", False)
        if interrupted and getattr(model, "num_timesteps", None) == getattr(self, "_sb3_cql_start_step", -1):
            # Ctrl-C before the first step (while the data were loaded or collected): no model to keep.
            removed = _remove_model_less_folder(self)
            gone = f", {removed} removed" if removed is not None else ""
            print(f"interrupted before training started: no model saved{gone}", file=sys.stderr)
            raise SystemExit(130)
        zoo["save_trained_model"](self, model)
        if self.algo not in ALGOS:
            return
        folder, env_id = Path(self.save_path), self.env_name.gym_id
        if getattr(self, "_sb3_cql_interrupted", False):
            step = model.num_timesteps
            best = " and the best evaluated so far, best_model.zip," if (folder / "best_model.zip").is_file() else ""
            print(f"interrupted at step {step} of {self.n_timesteps}: kept {folder / env_id}.zip (the model at that step)"
                  f"{best} in {folder}")  # fmt: skip
            raise SystemExit(130)  # the shell's status for a run ended by Ctrl-C
        best = f", {folder / 'best_model.zip'} (best evaluated)" if (folder / "best_model.zip").is_file() else ""
        print(f"models: {folder / env_id}.zip (last){best}")
        for line in _run_commands(self.algo, env_id, folder):
            print(line)

    ours = {wrapper.__name__: wrapper for wrapper in (__init__, read_hyperparameters, setup_experiment, create_log_folder,
                                                      create_envs, learn, save_trained_model)}  # fmt: skip
    assert set(ours) == set(zoo), "every wrapped method is named in ZOO_INTERNALS"
    for name, wrapper in ours.items():
        setattr(manager, name, functools.wraps(zoo[name])(wrapper))


_EXTENSIONS = {
    "rl_zoo3.utils": _extend_utils,
    "rl_zoo3.hyperparams_opt": _extend_hyperparams_opt,
    "rl_zoo3.exp_manager": _extend_exp_manager,
}

# ``import sb3_cql.zoo.plugin`` by hand (e.g. where the .pth file is not processed) extends the zoo modules already
# imported and hooks the others.
from sb3_cql.zoo import hook  # noqa: E402

hook.install()
