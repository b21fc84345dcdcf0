"""Each RL-Zoo3 and SB3 internal the zoo plugin relies on (``sb3_cql.zoo.internals.ZOO_INTERNALS``), checked against the
installed versions in seconds, without training: a zoo upgrade that changes one fails here by name."""

import argparse
import inspect
import os
import re
import runpy
import sys
import zipfile
from pathlib import Path

import gymnasium as gym
import optuna
import pytest
import rl_zoo3
import yaml
from rl_zoo3 import exp_manager, hyperparams_opt, train, utils
from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_cql.zoo import checkpoints, eval_freq, manager, plugin, pretrained, run_end
from sb3_cql.zoo.chunked import CHUNKED_KEY
from sb3_cql.zoo.eval_freq import CONFIG_OPTIONS
from sb3_cql.zoo.internals import ZOO_INTERNALS, zoo_internal
from sb3_cql.zoo.registry import hyperparams_dir

ZOO = f"rl_zoo3 {rl_zoo3.__version__}"
#: train.py's command line for a CQL run on Panda-v0 in the test's folder.
CQL_RUN = ["--algo", "cql", "--env", "Panda-v0", "-f", "logs", "--seed", "0"]
#: The behaviour entries of ZOO_INTERNALS, each with the test that checks it (filled by :func:`checks`).
BEHAVIOURS_CHECKED: dict[str, str] = {}


def checks(name: str):
    """Mark a test as the check of the ZOO_INTERNALS behaviour ``name``."""

    def mark(test):
        BEHAVIOURS_CHECKED[name] = test.__name__
        return test

    return mark


def of_kind(kind: str) -> list:
    return [internal for internal in ZOO_INTERNALS if internal.kind == kind]


class Stop(Exception):
    """Ends a zoo function at the point a test has what it wants."""


def zoo_parser() -> tuple[argparse.ArgumentParser, list[str] | None]:
    """``rl_zoo3.train``'s own parser (local to ``train()``), caught as ``train()`` parses, with what it parses."""
    caught = {}

    def catch(parser, args=None, namespace=None):
        caught.update(parser=parser, args=args)
        raise Stop

    original = argparse.ArgumentParser.parse_args
    argparse.ArgumentParser.parse_args = catch
    try:
        with pytest.raises(Stop):
            train.train()
    finally:
        argparse.ArgumentParser.parse_args = original
    return caught["parser"], caught["args"]


def made_by_train(monkeypatch, tmp_path: Path, *argv: str) -> ExperimentManager:
    """The ExperimentManager ``python -m rl_zoo3.train ARGV`` makes in ``tmp_path``, stopped before its setup."""
    made = []

    class Made(ExperimentManager):
        def setup_experiment(self):
            made.append(self)
            raise Stop

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(train, "ExperimentManager", Made)
    monkeypatch.setattr(sys, "argv", ["train", *argv])
    with pytest.raises(Stop):
        train.train()
    return made[0]


def tiny_sac(path: Path, env_id: str = "Pendulum-v1") -> Path:
    """An untrained SAC model on ``env_id`` saved at ``path``."""
    SAC("MlpPolicy", env_id, buffer_size=10, learning_starts=10, policy_kwargs={"net_arch": [4]}, device="cpu").save(path)
    return path.with_suffix(".zip")


def test_each_wrapped_method_is_the_zoos_with_the_parameters_the_plugin_binds():
    methods = {internal.name.removeprefix("ExperimentManager."): internal for internal in of_kind("method")}
    wrapped = {name for name, value in vars(ExperimentManager).items()
               if getattr(getattr(value, "__code__", None), "co_filename", None) == manager.__file__}  # fmt: skip
    assert wrapped == set(methods), f"the plugin wraps {sorted(wrapped)}, ZOO_INTERNALS names {sorted(methods)}"
    for name, internal in methods.items():
        original = getattr(ExperimentManager, name).__wrapped__
        assert original.__module__ == "rl_zoo3.exp_manager", f"{internal.name} wraps {original.__module__}'s"
        parameters = inspect.signature(original).parameters
        for parameter in internal.uses:
            assert parameter in parameters, f"{ZOO}: {internal.name} has no parameter {parameter!r}: update the plugin"
    assert manager.wrap_problems(ExperimentManager) == []


def test_a_zoo_without_a_wrapped_method_or_parameter_is_left_alone_with_a_warning():
    class Manager:
        def __init__(self, args, algo, env_id, log_folder): ...  # no config, no eval_env_kwargs

    assert manager.wrap_problems(Manager) == [
        "ExperimentManager.__init__ has no parameter 'config'",
        "ExperimentManager.__init__ has no parameter 'eval_env_kwargs'",
        "no ExperimentManager.read_hyperparameters",
        "no ExperimentManager.setup_experiment",
        "no ExperimentManager.create_log_folder",
        "no ExperimentManager.create_envs",
        "no ExperimentManager.learn",
        "no ExperimentManager.save_trained_model",
    ]
    module = type(sys)("rl_zoo3.exp_manager")
    module.ExperimentManager = Manager
    with pytest.warns(RuntimeWarning, match="sb3-cql's zoo plugin does not fit this rl_zoo3 .*has no parameter 'config'"):
        manager.extend_exp_manager(module)
    assert Manager.__init__.__module__ == __name__ and not hasattr(Manager.__init__, "__wrapped__")


def test_the_names_the_plugin_module_had_stay_importable_from_it():
    from sb3_cql.zoo import chunked, errors, internals, noise, registry

    homes = {chunked: ["CHUNKED_KEY"], errors: ["INPUT_ERRORS", "PROG", "SCHEDULE_KEYS", "ZOO_KEYS", "zoo_parse_error"],
             eval_freq: ["CONFIG_OPTIONS", "ZOO_DEFAULT_EVAL_EPISODES", "ZOO_DEFAULT_EVAL_FREQ", "ZOO_DEFAULT_SAVE_FREQ"],
             internals: ["ZOO_INTERNALS", "ZooInternal", "zoo_internal"], noise: ["PINK_SEQ_LEN"],
             registry: ["ALGO", "ALGOS", "config_file", "hyperparams_dir"]}  # fmt: skip
    for module, names in homes.items():
        for name in names:
            assert getattr(plugin, name) is getattr(module, name), name
    assert callable(plugin.extend)


def test_the_module_attributes_hold_our_algorithms_and_search_space():
    from sb3_cql.bc import BC
    from sb3_cql.cql import CQL
    from sb3_cql.iql import IQL
    from sb3_cql.zoo.search_space import convert_cql_params, convert_iql_params, sample_cql_params, sample_iql_params

    modules = {"rl_zoo3.utils": utils, "rl_zoo3.hyperparams_opt": hyperparams_opt}
    ours = {"ALGOS": {"cql": CQL, "bc": BC, "iql": IQL},
            "HYPERPARAMS_SAMPLER": {"cql": sample_cql_params, "iql": sample_iql_params},
            "HYPERPARAMS_CONVERTER": {"cql": convert_cql_params, "iql": convert_iql_params}}  # fmt: skip
    entries = [internal for internal in of_kind("attribute") if internal.name.startswith("rl_zoo3.")]
    assert {internal.name.rsplit(".", 1)[-1] for internal in entries} == set(ours)
    for internal in entries:
        module, name = internal.name.rsplit(".", 1)
        table = getattr(modules[module], name, None)
        assert isinstance(table, dict), f"{ZOO}: {internal.name} is not a dict any more"
        assert {key: table.get(key) for key in internal.uses} == ours[name], internal.name
    assert exp_manager.ALGOS is utils.ALGOS and train.ALGOS is utils.ALGOS  # the tables the zoo reads are ours
    assert exp_manager.HYPERPARAMS_SAMPLER is hyperparams_opt.HYPERPARAMS_SAMPLER
    assert exp_manager.HYPERPARAMS_CONVERTER is hyperparams_opt.HYPERPARAMS_CONVERTER


def test_the_manager_attributes_the_plugin_uses_are_set_by_the_zoos_own_init(monkeypatch, tmp_path):
    calls = []
    original_init = ExperimentManager.__init__.__wrapped__
    monkeypatch.setattr(
        ExperimentManager, "__init__", lambda self, *a, **k: calls.append((a, k)) or original_init(self, *a, **k)
    )
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    ((args, kwargs),) = calls
    assert inspect.signature(original_init).bind(manager, *args, **kwargs)  # train.py's call fits the signature
    for internal in of_kind("attribute"):
        if not internal.name.startswith("ExperimentManager."):
            continue
        attribute = internal.name.removeprefix("ExperimentManager.")
        assert attribute in vars(manager), f"{ZOO}: ExperimentManager.__init__ no longer sets {attribute}"
        for part in set(internal.uses) - {"read", "set"}:
            assert hasattr(getattr(manager, attribute), part), f"{ZOO}: {internal.name} has no {part}"
    assert isinstance(manager.args, argparse.Namespace) and manager.env_name.gym_id == "Panda-v0"
    assert (manager.trained_agent, manager.continue_training, manager.callbacks) == ("", False, [])


@checks("train.train parses sys.argv[1:]")
def test_train_parses_the_command_line_it_was_given():
    _, parsed = zoo_parser()
    assert parsed is None, f"{ZOO}: train() parses {parsed!r}, not sys.argv[1:]: the plugin reads sys.argv"


@pytest.mark.parametrize("internal", of_kind("option"), ids=lambda internal: internal.name)
def test_each_option_has_the_default_the_plugin_knows_and_sets_its_attribute(monkeypatch, tmp_path, internal):
    default, attribute = internal.uses
    parser, _ = zoo_parser()
    dest = internal.name.removeprefix("--").replace("-", "_")
    assert parser.get_default(dest) == default, (
        f"{ZOO}: train.py's {internal.name} defaults to {parser.get_default(dest)!r}, the plugin's ZOO_INTERNALS says "
        f"{default!r}: update ZOO_DEFAULT_* in sb3_cql/zoo/eval_freq.py"
    )
    if default is None:  # --env-kwargs: None in args when not given, a dict in the manager when given
        assert made_by_train(monkeypatch, tmp_path, *CQL_RUN).args.env_kwargs is None
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN, internal.name, "a:1"), attribute) == {"a": 1}
    else:
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN), attribute) == default
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN, internal.name, "7"), attribute) == 7


def test_config_options_are_options_of_train_with_an_attribute_and_config_key_of_one_name():
    for option in CONFIG_OPTIONS:
        internal = zoo_internal(option)
        assert internal.kind == "option" and isinstance(internal.uses[0], int), option
    assert [zoo_internal(option).uses[0] for option in CONFIG_OPTIONS] == [
        eval_freq.ZOO_DEFAULT_EVAL_FREQ,
        eval_freq.ZOO_DEFAULT_EVAL_EPISODES,
        eval_freq.ZOO_DEFAULT_SAVE_FREQ,
    ]
    with pytest.raises(KeyError, match="'--nothing' is not in ZOO_INTERNALS"):
        zoo_internal("--nothing")


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["--eval-freq", "100"],
        ["--eval-freq=100"],
        ["--eval-fr", "100"],
        ["--eval-episodes", "5"],
        ["--eval-ep=5"],
        ["--save-freq", "-1"],
        ["--save-f", "4000"],
        ["--save-replay-buffer"],
        ["--hyperparams", "eval_freq:75", "n_eval_episodes:1", "save_freq:10"],
        ["--eval-env-kwargs", "action_mode:'delta'"],
        ["-n", "100", "--env-kwargs", "action_mode:'delta'", "--eval-freq", "-1", "-tb", "tb"],
    ],
)
def test_options_given_are_read_from_the_command_line_as_the_zoos_parser_reads_it(argv):
    parser, _ = zoo_parser()
    unset = object()
    parser.set_defaults(**{option.removeprefix("--").replace("-", "_"): unset for option in CONFIG_OPTIONS})
    parsed = vars(parser.parse_args(argv))
    for option in CONFIG_OPTIONS:
        given = parsed[option.removeprefix("--").replace("-", "_")] is not unset
        assert eval_freq.given_on_command_line(option, argv) == given, (option, argv)


@checks("train.train calls learn, then save_trained_model")
def test_train_learns_then_saves_the_model_it_was_set_up_with(monkeypatch, tmp_path):
    steps, model = [], object()

    class Made(ExperimentManager):
        def setup_experiment(self):
            return model, {}

        def learn(self, model):
            steps.append(("learn", model))

        def save_trained_model(self, model):
            steps.append(("save_trained_model", model))

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(train, "ExperimentManager", Made)
    monkeypatch.setattr(sys, "argv", ["train", *CQL_RUN])
    train.train()
    assert steps == [("learn", model), ("save_trained_model", model)]


class Model:
    """A model whose training is cut short by Ctrl-C at once."""

    def __init__(self) -> None:
        self.env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
        self.learned_with: dict = {}

    def learn(self, total_timesteps, **kwargs):
        self.learned_with = kwargs
        raise KeyboardInterrupt


@checks("ExperimentManager.learn returns after Ctrl-C")
@checks("ExperimentManager.learn trains with self.callbacks")
def test_the_zoos_learn_returns_after_ctrl_c_having_trained_with_its_callbacks(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    manager.callbacks = [CheckpointCallback(save_freq=1, save_path=str(tmp_path))]
    model = Model()
    ExperimentManager.learn.__wrapped__(manager, model)  # returns: Ctrl-C does not propagate
    assert model.learned_with["callback"] is manager.callbacks
    manager.learn(Model())  # the plugin's, around it
    assert manager._sb3_cql_interrupted is False  # no SIGINT came: the zoo's own KeyboardInterrupt is not a Ctrl-C note


@checks("ExperimentManager.create_callbacks checkpoints as rl_model in save_path")
@checks("CheckpointCallback saves <prefix>_replay_buffer_<N>_steps.pkl")
def test_a_checkpoint_of_the_zoo_keeps_its_transitions_where_the_plugin_looks(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--save-freq", "2", "--eval-freq", "-1")
    manager.create_callbacks()
    (checkpoint,) = manager.callbacks
    assert isinstance(checkpoint, CheckpointCallback), f"{ZOO}: --save-freq made {manager.callbacks}"
    assert (checkpoint.name_prefix, checkpoint.save_path) == ("rl_model", manager.save_path)
    assert hasattr(checkpoint, "save_replay_buffer")
    checkpoint.save_replay_buffer = True  # as the plugin sets it for a fine-tuning
    model = SAC("MlpPolicy", "Pendulum-v1", buffer_size=10, learning_starts=10, policy_kwargs={"net_arch": [4]}, device="cpu")
    model.learn(2, callback=checkpoint)
    run = Path(manager.save_path)
    assert checkpoints.checkpoint_buffer(run / "rl_model_2_steps.zip") == run / "rl_model_replay_buffer_2_steps.pkl"


@checks("ExperimentManager._load_pretrained_agent loads replay_buffer.pkl beside the model")
def test_the_zoo_loads_the_replay_buffer_beside_an_i_model_and_the_plugin_then_loads_none(monkeypatch, tmp_path):
    loaded = []

    class Loaded:
        @classmethod
        def load(cls, path, **kwargs):
            return cls()

        def load_replay_buffer(self, path, **kwargs):
            loaded.append(Path(path))

    run = tmp_path / "run"
    run.mkdir()
    model_path = tiny_sac(run / "rl_model_2_steps")
    (run / "rl_model_replay_buffer_2_steps.pkl").write_bytes(b"")
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "-i", str(model_path))
    monkeypatch.setitem(exp_manager.ALGOS, "cql", Loaded)
    model = manager._load_pretrained_agent({"policy": "MlpPolicy"}, None)
    checkpoints.load_checkpoint_buffer(model, model_path)
    assert loaded == [run / "rl_model_replay_buffer_2_steps.pkl"]  # no replay_buffer.pkl: the checkpoint's
    (run / "replay_buffer.pkl").write_bytes(b"")
    loaded.clear()
    model = manager._load_pretrained_agent({"policy": "MlpPolicy"}, None)
    checkpoints.load_checkpoint_buffer(model, model_path)
    assert loaded == [run / "replay_buffer.pkl"]  # the zoo's only


@checks("ExperimentManager.setup_experiment loads -i with the env of create_envs(eval_env=False)")
def test_the_zoo_loads_an_i_model_with_its_training_env(monkeypatch, tmp_path):
    tiny_sac(tmp_path / "model")  # a model that opens: the plugin refuses a damaged one first
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "-i", "model.zip", "--eval-freq", "100")
    events, model = [], object()

    def create_envs(n_envs, eval_env=False, no_log=False):
        env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
        events.append(("create_envs", eval_env, env))
        return env

    def load(hyperparams, env):
        events.append(("load", hyperparams, env))
        return model

    manager.create_envs, manager._load_pretrained_agent = create_envs, load
    assert ExperimentManager.setup_experiment(manager)[0] is model
    (training_env,) = [env for event, eval_env, env in events if event == "create_envs" and not eval_env]
    assert events[-1][0] == "load" and events[-1][2] is training_env
    assert "eval_freq" not in events[-1][1] and "dataset" in events[-1][1]  # our keys out, the model's in


@checks("BaseAlgorithm.load checks spaces with check_for_correct_spaces")
def test_the_plugins_check_of_an_i_model_is_what_sb3_raises_when_it_loads_it(tmp_path):
    path = tiny_sac(tmp_path / "pendulum")
    envs = {"fits": lambda: gym.make("Pendulum-v1"),
            "other actions": lambda: gym.wrappers.RescaleAction(gym.make("Pendulum-v1"), -1.0, 1.0),
            "other observations": lambda: gym.make("MountainCarContinuous-v0")}  # fmt: skip
    saved = pretrained.saved_spaces(str(path))
    for name, make in envs.items():
        env = DummyVecEnv([make])
        misfit = pretrained.misfit(saved, env)
        if misfit is None:
            SAC.load(path, env=env, device="cpu")
            assert name == "fits"
            continue
        with pytest.raises(ValueError) as raised:
            SAC.load(path, env=env, device="cpu")
        assert " ".join(str(raised.value).split()) == misfit, name
    assert pretrained.misfit(None, env) is None


def test_an_i_model_that_does_not_fit_the_training_env_ends_the_run_on_one_line(monkeypatch, tmp_path, capsys):
    path = tiny_sac(tmp_path / "pendulum")
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "-i", str(path))
    manager.create_envs(1, eval_env=True, no_log=True).close()  # the evaluation env is not SB3's to check
    with pytest.raises(SystemExit) as ended:
        manager.create_envs(1, no_log=True)
    assert ended.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith(f"python -m rl_zoo3.train: error: {path} does not fit Panda-v0: Observation spaces do not match")


@checks("ExperimentManager._preprocess_hyperparams takes env_kwargs from read_hyperparameters")
def test_the_config_env_kwargs_reach_the_evaluation_env_and_its_keys_the_manager(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--eval-episodes", "5")
    hyperparams, saved = manager.read_hyperparameters()
    config = yaml.safe_load(Path(manager.config).read_text())["Panda-v0"]
    assert manager.config == str(hyperparams_dir() / "cql.yml")  # no --conf-file: ours
    assert not {"eval_freq", "n_eval_episodes"} & set(hyperparams) and saved["eval_freq"] == config["eval_freq"]
    assert (manager.eval_freq, manager.n_eval_episodes) == (config["eval_freq"], 5)  # the command line's 5 wins
    ExperimentManager._preprocess_hyperparams(manager, hyperparams)
    assert manager.env_kwargs == manager.eval_env_kwargs == manager.args.env_kwargs == config["env_kwargs"]

    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--eval-env-kwargs", "action_mode:'absolute'")
    ExperimentManager._preprocess_hyperparams(manager, manager.read_hyperparameters()[0])
    assert (manager.env_kwargs, manager.eval_env_kwargs) == (config["env_kwargs"], {"action_mode": "absolute"})


def test_a_conf_file_of_ours_not_in_the_working_folder_is_our_copy(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--conf-file", "cql_finetune.yml")
    assert manager.config == str(hyperparams_dir() / "cql_finetune.yml")
    (tmp_path / "mine.yml").write_text("Panda-v0: {policy: MlpPolicy, n_timesteps: 1}\n")
    assert made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--conf-file", "mine.yml").config == "mine.yml"


@checks("ExperimentManager._save_config writes args as args.yml, where record_video reads env_kwargs")
def test_the_config_env_kwargs_saved_in_args_yml_are_those_record_video_makes_its_env_with(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    _, saved = manager.read_hyperparameters()
    manager.create_log_folder()
    manager._save_config(saved)
    with zipfile.ZipFile(Path(manager.save_path, "Panda-v0.zip"), "w") as model:  # a model's members: found, not loaded
        model.writestr("data", "{}")
        model.writestr("policy.pth", b"")
    made_with = {}

    def create_test_env(env_id, **kwargs):
        made_with.update(kwargs["env_kwargs"])
        raise Stop

    monkeypatch.setattr(utils, "create_test_env", create_test_env)
    monkeypatch.setattr(sys, "argv", ["record_video", "--algo", "cql", "--env", "Panda-v0", "-f", "logs", "--exp-id", "1"])
    with pytest.raises(Stop):
        runpy.run_module("rl_zoo3.record_video", run_name="__main__")
    assert made_with == {**saved["env_kwargs"], "render_mode": "rgb_array"} and saved["env_kwargs"]


@checks("ExperimentManager.save_path is <log folder>/<algo>/<env id>_<N>")
def test_the_run_folder_gives_the_log_folder_and_exp_id_of_the_commands_printed(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    assert Path(manager.save_path) == Path("logs", "cql", "Panda-v0_1")
    Path(manager.save_path).mkdir(parents=True)
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    assert run_end.run_commands("cql", "Panda-v0", Path(manager.save_path))[1].endswith("-f logs --exp-id 2 -n 700")


@checks("ExperimentManager.setup_experiment uses save_path and params_path first in create_log_folder")
def test_a_run_whose_number_another_run_took_meanwhile_moves_to_the_next_with_every_path(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--save-freq", "2", "--eval-freq", "-1")
    assert Path(manager.save_path) == Path("logs", "cql", "Panda-v0_1")
    other = tmp_path / "logs" / "cql" / "Panda-v0_1"
    other.mkdir(parents=True)  # another run started with this one made its folder first
    seen = {}

    def create_envs(n_envs, eval_env=False, no_log=False):  # what the zoo makes next writes in save_path
        seen.update(save_path=manager.save_path, params_path=manager.params_path, callbacks=list(manager.callbacks))
        seen.update(params_folder=os.path.isdir(manager.params_path))
        raise Stop

    manager.create_envs = create_envs
    with pytest.raises(Stop):
        ExperimentManager.setup_experiment(manager)
    assert seen["save_path"] == os.path.join(manager.log_path, "Panda-v0_2")
    assert seen["params_path"] == f"{seen['save_path']}/Panda-v0" and seen["params_folder"]
    (checkpoint,) = seen["callbacks"]
    assert isinstance(checkpoint, CheckpointCallback) and checkpoint.save_path == seen["save_path"]
    assert other.is_dir() and not Path(seen["save_path"]).exists()  # the other run's kept; this one's, without a model, gone


@checks("the zoo saves the model it trains with model.save and model.save_replay_buffer")
def test_the_zoos_saves_of_a_model_go_through_its_class_which_the_plugin_makes_atomic(monkeypatch, tmp_path):
    written = []

    class Recording(SAC):
        def save(self, path, exclude=None, include=None):
            written.append(Path(path))
            super().save(path, exclude, include)

        def save_replay_buffer(self, path):
            written.append(Path(path))
            super().save_replay_buffer(path)

    manager = made_by_train(monkeypatch, tmp_path, "--algo", "sac", "--env", "Pendulum-v1", "-f", "logs", "--save-freq",
                            "2", "--eval-freq", "2", "--eval-episodes", "1", "--save-replay-buffer")  # fmt: skip
    manager.create_log_folder()
    manager.create_callbacks()
    assert [type(callback) for callback in manager.callbacks] == [CheckpointCallback, EvalCallback]
    manager.callbacks[0].save_replay_buffer = True
    model = Recording("MlpPolicy", "Pendulum-v1", buffer_size=10, learning_starts=10, policy_kwargs={"net_arch": [4]})
    checkpoints.atomic_saves(model)
    assert isinstance(model, Recording) and type(model).__name__ == "Recording" and type(model).saves_atomically
    model.learn(2, callback=manager.callbacks)
    manager.save_trained_model(model)
    run = Path(manager.save_path)
    # Each file written under a temporary name beside its own, then renamed: none is left.
    finals = [re.fullmatch(r"\.(.+)\.\d+-[0-9a-f]{8}\.tmp", path.name)[1] for path in written]
    assert {path.parent for path in written} == {run}
    assert finals == ["rl_model_2_steps.zip", "rl_model_replay_buffer_2_steps.pkl", "best_model.zip", "Pendulum-v1.zip",
                      "replay_buffer.pkl"]  # fmt: skip
    assert sorted(path.name for path in run.iterdir() if path.suffix in (".zip", ".pkl", ".tmp")) == sorted(finals)


@checks("ExperimentManager.objective calls the sampler with (trial, n_actions, n_envs, additional_args)")
def test_tuning_samples_cql_with_the_zoos_arguments_and_reads_a_trial_back_with_our_converter(monkeypatch, tmp_path):
    from sb3_cql.zoo.search_space import convert_cql_params, sample_cql_params

    called = []

    def sample(*args):
        called.append(args)
        raise Stop

    storage = f"sqlite:///{tmp_path / 'study.db'}"
    study = optuna.create_study(storage=storage, study_name="cql", sampler=optuna.samplers.RandomSampler(seed=0))
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "-optimize")
    manager._hyperparams, manager.n_actions = {}, 9
    monkeypatch.setitem(hyperparams_opt.HYPERPARAMS_SAMPLER, "cql", sample)
    with pytest.raises(Stop):
        manager.objective(study.ask())
    ((trial, n_actions, n_envs, additional_args),) = called
    assert isinstance(trial, optuna.Trial) and (n_actions, n_envs) == (9, 1) and isinstance(additional_args, dict)
    assert "cql_alpha" in sample_cql_params(trial, n_actions, n_envs, additional_args)  # ours takes the zoo's call
    study.tell(trial, 1.0)
    assert manager.load_trial(storage, "cql", trial_id=0) == convert_cql_params(trial.params)


def test_every_behaviour_in_zoo_internals_has_its_check():
    behaviours = {internal.name for internal in of_kind("behaviour")}
    assert set(BEHAVIOURS_CHECKED) == behaviours, (
        f"without a check: {sorted(behaviours - set(BEHAVIOURS_CHECKED))}; "
        f"checked but not in ZOO_INTERNALS: {sorted(set(BEHAVIOURS_CHECKED) - behaviours)}"
    )
    assert {internal.kind for internal in ZOO_INTERNALS} == {"method", "attribute", "option", "behaviour"}
    assert all(internal.reason for internal in ZOO_INTERNALS)
    assert len({internal.name for internal in ZOO_INTERNALS}) == len(ZOO_INTERNALS)


FINETUNE_RUN = ["--algo", "cql", "--env", "PandaForce-v0", "--conf-file", "cql_finetune.yml", "-f", "logs", "--seed", "0"]


def tiny_chunked_cql(path: Path) -> Path:
    """An untrained CQL model of action chunks of 3 on Pendulum saved at ``path``."""
    from sb3_cql import CQL

    CQL("MlpPolicy", "Pendulum-v1", buffer_size=10, action_chunk=3, policy_kwargs={"net_arch": [4]}, device="cpu").save(path)
    return path.with_suffix(".zip")


@checks("ExperimentManager.read_hyperparameters applies --hyperparams before returning")
def test_a_chunked_i_model_gets_the_configs_chunked_settings_below_the_command_lines(monkeypatch, tmp_path):
    config = yaml.safe_load((hyperparams_dir() / "cql_finetune.yml").read_text())["PandaForce-v0"]
    chunked, given = tiny_chunked_cql(tmp_path / "chunked"), ["--hyperparams", "gradient_steps:3"]
    manager = made_by_train(monkeypatch, tmp_path, *FINETUNE_RUN, "-i", str(chunked), *given)
    zoos, _ = ExperimentManager.read_hyperparameters.__wrapped__(manager)  # the zoo's own, before the plugin's part
    assert zoos["gradient_steps"] == 3 and zoos[CHUNKED_KEY] == config[CHUNKED_KEY]
    manager = made_by_train(monkeypatch, tmp_path, *FINETUNE_RUN, "-i", str(chunked), *given)
    hyperparams, saved = manager.read_hyperparameters()
    assert (hyperparams["train_freq"], hyperparams["gradient_steps"]) == (config["chunked"]["train_freq"], 3)
    assert CHUNKED_KEY not in hyperparams and CHUNKED_KEY not in saved
    assert saved["noise_type"] == "pink" and "noise_type" not in hyperparams  # the zoo knows no pink noise
    assert manager._sb3_cql_noise == ("pink", config["chunked"]["noise_std"], 1)
    assert (manager.eval_freq, manager.save_freq) == (config["chunked"]["eval_freq"], config["chunked"]["save_freq"])
    # A model of one action a state keeps the entry's own settings.
    manager = made_by_train(monkeypatch, tmp_path, *FINETUNE_RUN, "-i", str(tiny_sac(tmp_path / "sac")))
    hyperparams, _ = manager.read_hyperparameters()
    assert (hyperparams["train_freq"], hyperparams["noise_type"]) == (config["train_freq"], config["noise_type"])
    assert manager.eval_freq == config["eval_freq"]


@checks("ExperimentManager._preprocess_action_noise knows normal and ornstein-uhlenbeck only")
def test_the_zoo_makes_normal_and_ou_noise_only_and_leaves_unknown_keys_to_the_model(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
    with pytest.raises(RuntimeError, match="pink"):
        ExperimentManager._preprocess_action_noise(manager, {"noise_type": "pink", "noise_std": 0.1}, {}, env)
    made = ExperimentManager._preprocess_action_noise(
        manager, {"noise_type": "normal", "noise_std": 0.1, "noise_hold": 5}, {}, env
    )
    assert made["noise_hold"] == 5  # the model would get it: the plugin takes it out first


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (["noise_hold:0"], "noise_hold must be an integer >= 1, got 0"),
        (["noise_type:'pink'", "noise_std:-1"], "noise_type pink needs noise_std >= 0, got -1"),
        (["noise_type:None", "noise_hold:5"], "noise_hold holds the draws of a noise_type: give one"),
    ],
)
def test_bad_noise_settings_end_the_run_on_one_line(monkeypatch, tmp_path, settings, message):
    manager = made_by_train(monkeypatch, tmp_path, *FINETUNE_RUN, "--hyperparams", *settings)
    with pytest.raises(SystemExit, match=f"^python -m rl_zoo3.train: error: {message}$"):
        manager.read_hyperparameters()


@checks("train.py reads --hyperparams and --env-kwargs with utils.StoreDict, which evals each VALUE")
def test_train_reads_key_value_items_with_store_dict_and_a_value_that_does_not_evaluate_is_one_line(
    monkeypatch, tmp_path, capsys
):
    parser, _ = zoo_parser()
    actions = {action.dest: action for action in parser._actions}
    assert isinstance(actions["hyperparams"], utils.StoreDict) and isinstance(actions["env_kwargs"], utils.StoreDict)
    made = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--hyperparams", "batch_size:2*32")
    assert made.custom_hyperparams == {"batch_size": 64}  # evaluated as Python
    with pytest.raises(SystemExit) as exit_:
        made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--env-kwargs", "action_mode:delta")
    assert exit_.value.code == 2
    assert capsys.readouterr().err.splitlines() == [
        "python -m rl_zoo3.train: error: --env-kwargs action_mode:delta: NameError: name 'delta' is not defined; write "
        "KEY:VALUE with a Python value: a number as it is (batch_size:64), a string in quotes inside the shell's "
        "(action_mode:\"'delta'\")"
    ]


@checks("enjoy.py and record_video.py find the model they load with utils.get_model_path")
def test_enjoy_finds_its_model_with_get_model_path_and_a_damaged_one_is_one_line(monkeypatch, tmp_path, capsys):
    from rl_zoo3 import enjoy, record_video

    assert enjoy.get_model_path is utils.get_model_path and record_video.get_model_path is utils.get_model_path
    run = tmp_path / "logs" / "sac" / "Pendulum-v1_1"
    run.mkdir(parents=True)
    whole = tiny_sac(run / "best_model").read_bytes()
    (run / "best_model.zip").write_bytes(whole[: len(whole) // 2])
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["enjoy", "--algo", "sac", "--env", "Pendulum-v1", "-f", "logs", "--exp-id", "1",
                                      "--load-best", "-n", "1"])  # fmt: skip
    with pytest.raises(SystemExit) as exit_:
        enjoy.enjoy()
    assert exit_.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"python -m rl_zoo3.enjoy: error: {Path('logs/sac/Pendulum-v1_1/best_model.zip')} cannot be "
                           "loaded: it ") and line.endswith("; no checkpoint beside it opens")  # fmt: skip
