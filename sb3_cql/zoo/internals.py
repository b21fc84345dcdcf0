"""Everything of RL-Zoo3 and SB3 the zoo plugin relies on beyond their documented use (:data:`ZOO_INTERNALS`), each
checked against the installed versions by ``tests/test_zoo_internals.py``: a zoo upgrade that changes one fails there
by name."""

from __future__ import annotations

from typing import Any, NamedTuple

from sb3_cql.zoo.plugin import OPTIONS


class ZooInternal(NamedTuple):
    """A part of RL-Zoo3 (or SB3) at ``name`` the plugin relies on, ``uses`` what of it, for ``reason``. ``kind``:
    ``"method"``, an ``ExperimentManager`` method our subclass overrides (``uses``: parameters it names);
    ``"attribute"``, one it reads or sets; ``"option"``, an option of ``rl_zoo3.train`` (``uses``: its default and the
    attribute it sets); ``"behaviour"``, something the zoo's or SB3's code does."""

    kind: str
    name: str
    uses: tuple[Any, ...]
    reason: str


B = "behaviour"
#: Everything of RL-Zoo3 and SB3 the plugin relies on beyond their documented use.
ZOO_INTERNALS: tuple[ZooInternal, ...] = (
    ZooInternal("method", "ExperimentManager.__init__", ("args", "algo", "env_id", "config"), "our config as the default"),
    ZooInternal("method", "ExperimentManager.read_hyperparameters", (), "a config's option keys, env_kwargs and schedules"),
    ZooInternal("method", "ExperimentManager.create_log_folder", (), "the run's folder claimed with os.mkdir"),
    ZooInternal("method", "ExperimentManager.setup_experiment", (), "a damaged -i model or an error of the input: one line"),
    ZooInternal("method", "ExperimentManager.learn", ("model",), "a fine-tuning's checkpoints keep its transitions"),
    ZooInternal("method", "ExperimentManager.save_trained_model", ("model",), "a full disk: one line, no empty run"),
    ZooInternal("attribute", "rl_zoo3.utils.ALGOS", ("cql", "calql", "bc", "iql"), "--algo's choices, the classes used"),
    ZooInternal("attribute", "rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER", ("cql", "calql", "iql"), "our samplers"),
    ZooInternal("attribute", "rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER", ("cql", "calql", "iql"), "a trial read"),
    ZooInternal("attribute", "rl_zoo3.utils.StoreDict", ("__call__",), "a VALUE that does not evaluate: one line"),
    ZooInternal("attribute", "rl_zoo3.utils.SimpleLinearSchedule", ("__call__",), "the actor's lin_<x> schedule"),
    ZooInternal("attribute", "ExperimentManager", ("args", "eval_env_kwargs", "env_name", "save_path", "params_path",
                "log_path", "trained_agent", "continue_training", "callbacks"), "set by __init__, read or set by ours"),
    *(ZooInternal("option", option, (default, key), f"a config's {key} where the option is not given")
      for key, (option, default) in OPTIONS.items()),
    ZooInternal("option", "--env-kwargs", (None, "env_kwargs"), "None when not given: the config's go to args.yml"),
    ZooInternal("option", "--eval-env-kwargs", (None, "eval_env_kwargs"), "None when not given: the config's apply"),
    ZooInternal(B, "train.py imports ExperimentManager from rl_zoo3.exp_manager", (), "the plugin puts ours there first"),
    ZooInternal(B, "train.train parses sys.argv[1:]", (), "which options were given: its Namespace has values only"),
    ZooInternal(B, "train.py reads --hyperparams and --env-kwargs with utils.StoreDict", (), "StoreDict evals each VALUE"),
    ZooInternal(B, "ExperimentManager.read_hyperparameters applies --hyperparams", (), "their keys are read as the config's"),
    ZooInternal(B, "ExperimentManager._preprocess_schedules reads learning_rate 'lin_<x>'", (), "ours reads the others"),
    ZooInternal(B, "ExperimentManager._preprocess_hyperparams takes env_kwargs from read_hyperparameters", (), "eval's too"),
    ZooInternal(B, "record_video reads env_kwargs from the args.yml that ExperimentManager._save_config writes", (),
                "a run's videos are recorded in the action mode it was trained in"),
    ZooInternal(B, "ExperimentManager.save_path is <log folder>/<algo>/<env id>_<N>", (), "the next number is N + 1"),
    ZooInternal(B, "ExperimentManager.setup_experiment calls create_log_folder before it writes", (),
                "the folder claimed there is the one the run's callbacks, monitor, config and models are written in"),
    ZooInternal(B, "ExperimentManager.learn trains with self.callbacks", (), "the checkpoints set to keep transitions run"),
    ZooInternal(B, "ExperimentManager.create_callbacks checkpoints as rl_model in save_path", (), "SB3's names, below"),
    ZooInternal(B, "CheckpointCallback saves <prefix>_replay_buffer_<N>_steps.pkl", (), "the name -i CHECKPOINT looks for"),
    ZooInternal(B, "ExperimentManager._load_pretrained_agent loads replay_buffer.pkl beside -i", (), "else a checkpoint's"),
    ZooInternal(B, "the zoo makes, loads and saves its models through ALGOS[algo]", (), "whose classes save whole"),
    ZooInternal(B, "utils.get_callback_list makes a config's callback: entries with their keywords", (), "ExplorationNoise"),
    ZooInternal(B, "OffPolicyAlgorithm.learn reads action_noise after the callbacks start", (), "ExplorationNoise's is used"),
    ZooInternal(B, "ExperimentManager.objective calls the sampler with (trial, n_actions, n_envs, additional_args)", (),
                "our samplers' signature"),
)  # fmt: skip
