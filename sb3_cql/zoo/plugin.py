"""What the package adds to RL-Zoo3: ``cql`` and ``bc`` in ``ALGOS``, the Panda tasks, the CQL search space, and our
``hyperparams/`` files as the default config of our algorithms and tasks.

:func:`extend` is called by :mod:`sb3_cql.zoo.hook` right after each zoo module in ``hook.TRIGGERS`` is imported;
``import sb3_cql.zoo.plugin`` extends whichever of them are already loaded and installs the hook for the others.
"""

from __future__ import annotations

import functools
import inspect
import shutil
import signal
import sys
import threading
from pathlib import Path
from types import ModuleType
from typing import Any

#: The algorithm the package adds to the zoo, with its search space.
ALGO = "cql"
#: Every algorithm the package adds: our config file is their default config on any env.
ALGOS = (ALGO, "bc")
#: ``train.py``'s defaults of ``--eval-freq`` and ``--eval-episodes``: a config's ``eval_freq`` / ``n_eval_episodes``
#: replace them; a value given on the command line (or any other value) wins over the config.
ZOO_DEFAULT_EVAL_FREQ, ZOO_DEFAULT_EVAL_EPISODES = 25_000, 5
#: ``train.py``'s default of ``--save-freq`` (no checkpoints): a config's ``save_freq`` replaces it.
ZOO_DEFAULT_SAVE_FREQ = -1


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

    utils.ALGOS.setdefault(ALGO, CQL)
    utils.ALGOS.setdefault("bc", BC)


def _extend_hyperparams_opt(hyperparams_opt: ModuleType) -> None:
    from sb3_cql.zoo.search_space import convert_cql_params, sample_cql_params

    hyperparams_opt.HYPERPARAMS_SAMPLER.setdefault(ALGO, sample_cql_params)
    hyperparams_opt.HYPERPARAMS_CONVERTER.setdefault(ALGO, convert_cql_params)


def _left_at_default(option: str, value: Any, default: Any) -> bool:
    """Whether the zoo's ``option`` has its default ``value`` and was not written on the command line (where a value
    equal to the default is still the user's choice)."""
    return value == default and not any(arg == option or arg.startswith(f"{option}=") for arg in sys.argv[1:])


def _our_config(config: str) -> str:
    """``config`` (``--conf-file``), or where it names one of our files that is not there (``cql_finetune.yml``
    outside the source tree), our installed copy of it."""
    ours = hyperparams_dir() / Path(config).name
    return str(ours) if not Path(config).exists() and ours.is_file() else config


def _checkpoint_buffer(model_path: Path) -> Path | None:
    """The replay buffer saved with a checkpoint ``rl_model_<N>_steps.zip`` (SB3's ``CheckpointCallback``), if any."""
    parts = model_path.stem.rsplit("_", 2)  # rl_model, <N>, steps
    if len(parts) != 3 or parts[2] != "steps" or not parts[1].isdigit():
        return None
    path = model_path.with_name(f"{parts[0]}_replay_buffer_{parts[1]}_steps.pkl")
    return path if path.is_file() else None


def _holds_a_model(folder: Path) -> bool:
    """Whether a zoo run folder holds a saved model (any ``.zip``): a run that got as far as its first checkpoint."""
    return any(folder.rglob("*.zip"))


def _run_commands(algo: str, env_id: str, save_path: Path) -> list[str]:
    """What to do with a run's models: evaluate on the three tasks, record a video (the zoo's own ``--exp-id``)."""
    log_folder, exp_id = save_path.parent.parent, save_path.name.rsplit("_", 1)[-1]
    model = save_path / ("best_model.zip" if (save_path / "best_model.zip").is_file() else f"{env_id}.zip")
    return [
        f"evaluate on the three tasks: python -m sb3_cql.evaluate {model} --algo {algo} -n 100",
        f"record a video: python -m rl_zoo3.record_video --algo {algo} --env {env_id} -f {log_folder} --exp-id {exp_id}"
        f"{' --load-best' if model.name == 'best_model.zip' else ''} -n 700",
    ]


def _extend_exp_manager(exp_manager: ModuleType) -> None:
    from stable_baselines3.common.callbacks import CheckpointCallback

    manager = exp_manager.ExperimentManager
    init, preprocess = manager.__init__, manager._preprocess_hyperparams
    setup, learn, save = manager.setup_experiment, manager.learn, manager.save_trained_model
    load_pretrained = manager._load_pretrained_agent
    init_signature = inspect.signature(init)

    @functools.wraps(init)
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        if init_signature.bind(self, *args, **kwargs).arguments.get("config") is None:  # no --conf-file
            ours = config_file(self.algo, self.env_name.gym_id)
            if ours is not None:
                self.config = str(ours)
        else:
            self.config = _our_config(self.config)

    @functools.wraps(preprocess)
    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        # Evaluation settings in a config: the zoo has command-line flags for them only.
        eval_freq, n_eval_episodes = hyperparams.pop("eval_freq", None), hyperparams.pop("n_eval_episodes", None)
        if eval_freq is not None and _left_at_default("--eval-freq", self.eval_freq, ZOO_DEFAULT_EVAL_FREQ):
            self.eval_freq = int(eval_freq)
        if n_eval_episodes is not None and _left_at_default(
            "--eval-episodes", self.n_eval_episodes, ZOO_DEFAULT_EVAL_EPISODES
        ):
            self.n_eval_episodes = int(n_eval_episodes)
        save_freq = hyperparams.pop("save_freq", None)
        if save_freq is not None and _left_at_default("--save-freq", self.save_freq, ZOO_DEFAULT_SAVE_FREQ):
            self.save_freq = int(save_freq)
        result = preprocess(self, hyperparams)
        if self._eval_env_kwargs_args is None:
            # The zoo gives a config's env_kwargs to the training env only (it copied the empty command-line value
            # to the evaluation env before reading the config): evaluate in the env trained in (e.g. its action mode).
            self.eval_env_kwargs = self.env_kwargs
        if self.env_kwargs and getattr(self.args, "env_kwargs", None) is None:
            # Recorded in the run's args.yml too: record_video reads env_kwargs from there only, not from config.yml.
            self.args.env_kwargs = self.env_kwargs
        return result

    @functools.wraps(setup)
    def setup_experiment(self) -> Any:
        # The zoo makes the run's folder before the model, whose dataset may first be collected: a run stopped there
        # (Ctrl-C, an error) would leave a folder without a model, and shift the next run's number.
        try:
            return setup(self)
        except BaseException as error:
            folder = Path(self.save_path)
            if folder.is_dir() and not _holds_a_model(folder):
                shutil.rmtree(folder, ignore_errors=True)
            if isinstance(error, KeyboardInterrupt):
                if not getattr(error, "said", False):  # a dataset collection says what it kept itself
                    print(f"interrupted before training started: no model yet, {folder} removed", file=sys.stderr)
                raise SystemExit(130) from None
            raise

    @functools.wraps(load_pretrained)
    def _load_pretrained_agent(self, hyperparams: dict[str, Any], env: Any) -> Any:
        # -i MODEL: a model that does not fit the env gets one line (SB3 raises on its spaces); a checkpoint of an
        # online fine-tuning continues with the online transitions saved beside it.
        try:
            model = load_pretrained(self, hyperparams, env)
        except ValueError as error:
            if "spaces do not match" not in str(error):
                raise
            print(f"python -m rl_zoo3.train: error: {self.trained_agent} does not fit {self.env_name.gym_id} "
                  f"{self.env_kwargs or ''}: {' '.join(str(error).split())}", file=sys.stderr)  # fmt: skip
            raise SystemExit(2) from None
        buffer = _checkpoint_buffer(Path(self.trained_agent))
        beside = Path(self.trained_agent).with_name("replay_buffer.pkl")
        if getattr(model, "online_fraction", None) is not None and buffer is not None and not beside.is_file():
            print(f"Loading the replay buffer of the checkpoint: {buffer}")
            model.load_replay_buffer(buffer)
        return model

    @functools.wraps(learn)
    def learn_(self, model: Any) -> None:
        if getattr(model, "online_fraction", None) is not None:
            # Online fine-tuning: a checkpoint keeps the online transitions too, to continue from (-i CHECKPOINT).
            for callback in self.callbacks:
                if isinstance(callback, CheckpointCallback):
                    callback.save_replay_buffer = True
        # The zoo ends training quietly on Ctrl-C (it catches KeyboardInterrupt) and saves the model: note that it
        # was cut short, to say so after the save.
        self._sb3_cql_interrupted = False
        if threading.current_thread() is not threading.main_thread():
            learn(self, model)
            return

        def note_and_interrupt(signum: int, frame: Any) -> None:
            self._sb3_cql_interrupted = True
            raise KeyboardInterrupt

        previous = signal.signal(signal.SIGINT, note_and_interrupt)
        try:
            learn(self, model)
        finally:
            signal.signal(signal.SIGINT, previous)

    @functools.wraps(save)
    def save_trained_model(self, model: Any) -> None:
        save(self, model)
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

    manager.__init__ = __init__
    manager._preprocess_hyperparams = _preprocess_hyperparams
    manager.setup_experiment = setup_experiment
    manager.learn = learn_
    manager._load_pretrained_agent = _load_pretrained_agent
    manager.save_trained_model = save_trained_model


_EXTENSIONS = {
    "rl_zoo3.utils": _extend_utils,
    "rl_zoo3.hyperparams_opt": _extend_hyperparams_opt,
    "rl_zoo3.exp_manager": _extend_exp_manager,
}

# ``import sb3_cql.zoo.plugin`` by hand (e.g. where the .pth file is not processed) extends the zoo modules already
# imported and hooks the others.
from sb3_cql.zoo import hook  # noqa: E402

hook.install()
