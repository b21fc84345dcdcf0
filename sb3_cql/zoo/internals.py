"""Everything of RL-Zoo3 and SB3 the zoo plugin relies on beyond their documented use (:data:`ZOO_INTERNALS`), each
checked against the installed versions by ``tests/test_zoo_internals.py``: a zoo upgrade that changes one fails there
by name. The plugin wraps public ``ExperimentManager`` methods only and matches no error text."""

from __future__ import annotations

from typing import Any, NamedTuple

from sb3_cql.zoo.eval_freq import CONFIG_OPTIONS
from sb3_cql.zoo.registry import ALGO, ALGOS


class ZooInternal(NamedTuple):
    """A part of RL-Zoo3 (or SB3) the plugin relies on that a new version could change without notice.

    :param kind: ``"method"``: an ``ExperimentManager`` method the plugin wraps, ``uses`` the parameters it binds by
        name; ``"attribute"``: one it reads or sets, ``uses`` what of it; ``"option"``: an option of ``rl_zoo3.train``,
        ``uses`` its default and the ``ExperimentManager`` attribute (and config key) it sets; ``"behaviour"``:
        something the zoo's or SB3's code does that the plugin builds on.
    :param name: where it is.
    :param uses: what of it the plugin uses.
    :param reason: why the plugin needs it.
    """

    kind: str
    name: str
    uses: tuple[Any, ...]
    reason: str


#: Everything of RL-Zoo3 and SB3 the plugin relies on beyond their documented use.
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
    *(ZooInternal("option", option, uses, f"a config's {uses[1]} replaces the default")
      for option, uses in CONFIG_OPTIONS.items()),
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


def zoo_internal(name: str) -> ZooInternal:
    """The entry of :data:`ZOO_INTERNALS` named ``name``."""
    for internal in ZOO_INTERNALS:
        if internal.name == name:
            return internal
    raise KeyError(f"{name!r} is not in ZOO_INTERNALS")
