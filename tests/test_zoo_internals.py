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
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_cql.zoo import plugin
from sb3_cql.zoo.callbacks import ExplorationNoise
from sb3_cql.zoo.internals import ZOO_INTERNALS
from sb3_cql.zoo.plugin import OPTIONS, ExperimentManager, hyperparams_dir

ZOO = f"rl_zoo3 {rl_zoo3.__version__}"
#: The zoo's own ExperimentManager, which ours subclasses.
ZooExperimentManager = ExperimentManager.__mro__[1]
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


def zoo_internal(name: str):
    (internal,) = [internal for internal in ZOO_INTERNALS if internal.name == name]
    return internal


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


def test_each_overridden_method_is_the_zoos_with_the_parameters_ours_names():
    methods = {internal.name.removeprefix("ExperimentManager."): internal for internal in of_kind("method")}
    overridden = {name for name, value in vars(ExperimentManager).items() if callable(value) and not name.startswith("_")}
    assert overridden | {"__init__"} == set(methods), f"ours overrides {sorted(overridden)}, ZOO_INTERNALS names {methods}"
    for name, internal in methods.items():
        zoos = getattr(ZooExperimentManager, name)
        assert zoos.__module__ == "rl_zoo3.exp_manager", f"{ZOO}: no ExperimentManager.{name} of its own"
        parameters = inspect.signature(zoos).parameters
        for parameter in internal.uses:
            assert parameter in parameters, f"{ZOO}: {internal.name} has no parameter {parameter!r}: update the plugin"


@checks("train.py imports ExperimentManager from rl_zoo3.exp_manager")
def test_the_zoo_makes_our_experiment_manager():
    assert ZooExperimentManager.__module__ == "rl_zoo3.exp_manager" and ZooExperimentManager.__name__ == "ExperimentManager"
    assert exp_manager.ExperimentManager is ExperimentManager and train.ExperimentManager is ExperimentManager
    assert "from rl_zoo3.exp_manager import ExperimentManager" in Path(train.__file__).read_text()


def test_the_module_attributes_hold_our_algorithms_and_search_space():
    from sb3_cql.bc import BC
    from sb3_cql.cql import CQL, CalQL
    from sb3_cql.iql import IQL
    from sb3_cql.zoo.search_space import convert_params, sample_cql_params, sample_iql_params

    modules = {"rl_zoo3.utils": utils, "rl_zoo3.hyperparams_opt": hyperparams_opt}
    expected = {"ALGOS": {"cql": CQL, "calql": CalQL, "bc": BC, "iql": IQL},
                "HYPERPARAMS_SAMPLER": {"cql": sample_cql_params, "calql": sample_cql_params, "iql": sample_iql_params},
                "HYPERPARAMS_CONVERTER": {"cql": convert_params, "calql": convert_params, "iql": convert_params}}  # fmt: skip
    tables = [internal for internal in of_kind("attribute") if internal.name.rsplit(".", 1)[-1] in expected]
    assert {internal.name.rsplit(".", 1)[-1] for internal in tables} == set(expected)
    for internal in tables:
        module, name = internal.name.rsplit(".", 1)
        table = getattr(modules[module], name, None)
        assert isinstance(table, dict), f"{ZOO}: {internal.name} is not a dict any more"
        assert {key: table.get(key) for key in internal.uses} == expected[name], internal.name
    assert exp_manager.ALGOS is utils.ALGOS and train.ALGOS is utils.ALGOS  # the tables the zoo reads are ours
    assert exp_manager.HYPERPARAMS_SAMPLER is hyperparams_opt.HYPERPARAMS_SAMPLER
    assert exp_manager.HYPERPARAMS_CONVERTER is hyperparams_opt.HYPERPARAMS_CONVERTER
    for name in ("StoreDict", "SimpleLinearSchedule"):
        (uses,) = zoo_internal(f"rl_zoo3.utils.{name}").uses
        assert callable(getattr(getattr(utils, name), uses, None)), f"{ZOO}: utils.{name}.{uses}"
    plugin.register()  # again: nothing changes
    assert utils.ALGOS["cql"] is CQL and utils.StoreDict.__call__.__wrapped__.__module__ == "rl_zoo3.utils"


def test_the_manager_attributes_ours_uses_are_set_by_the_zoos_own_init(monkeypatch, tmp_path):
    calls, zoos_init = [], ZooExperimentManager.__init__

    def recording_init(self, *args, **kwargs):
        calls.append((args, kwargs))
        zoos_init(self, *args, **kwargs)

    monkeypatch.setattr(ZooExperimentManager, "__init__", recording_init)
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    ((args, kwargs),) = calls
    assert inspect.signature(zoos_init).bind(manager, *args, **kwargs)  # ours passes on what train.py gave
    for attribute in zoo_internal("ExperimentManager").uses:
        assert attribute in vars(manager), f"{ZOO}: ExperimentManager.__init__ no longer sets {attribute}"
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
        f"{ZOO}: train.py's {internal.name} defaults to {parser.get_default(dest)!r}, ZOO_INTERNALS says {default!r}: "
        "update OPTIONS in sb3_cql/zoo/plugin.py"
    )
    if default is None:  # the kwargs options: None in args when not given, a dict in the manager when given
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN).args, dest) is None
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN, internal.name, "a:1"), attribute) == {"a": 1}
    else:
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN), attribute) == default
        assert getattr(made_by_train(monkeypatch, tmp_path, *CQL_RUN, internal.name, "7"), attribute) == 7


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
    parser.set_defaults(**{option.removeprefix("--").replace("-", "_"): unset for option, _ in OPTIONS.values()})
    parsed = vars(parser.parse_args(argv))
    for option, _ in OPTIONS.values():
        given = parsed[option.removeprefix("--").replace("-", "_")] is not unset
        assert plugin.given_on_command_line(option, argv) == given, (option, argv)


class Model:
    """A model whose training is cut short by Ctrl-C at once."""

    def __init__(self) -> None:
        self.env = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
        self.learned_with: dict = {}
        self.num_timesteps = 0

    def learn(self, total_timesteps, **kwargs):
        self.learned_with = kwargs
        raise KeyboardInterrupt


@checks("ExperimentManager.learn trains with self.callbacks")
def test_the_zoos_learn_trains_with_its_callbacks(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    manager.callbacks = [CheckpointCallback(save_freq=1, save_path=str(tmp_path))]
    model = Model()
    manager.learn(model)  # returns: the zoo takes Ctrl-C to save the model, and no SIGINT came
    assert model.learned_with["callback"] is manager.callbacks


@checks("ExperimentManager.create_callbacks checkpoints as rl_model in save_path")
@checks("CheckpointCallback saves <prefix>_replay_buffer_<N>_steps.pkl")
def test_a_checkpoint_of_the_zoo_keeps_its_transitions_where_the_plugin_looks(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--save-freq", "2", "--eval-freq", "-1")
    manager.create_callbacks()
    (checkpoint,) = manager.callbacks
    assert isinstance(checkpoint, CheckpointCallback), f"{ZOO}: --save-freq made {manager.callbacks}"
    assert (checkpoint.name_prefix, checkpoint.save_path) == ("rl_model", manager.save_path)
    checkpoint.save_replay_buffer = True  # as the plugin sets it for a fine-tuning
    model = SAC("MlpPolicy", "Pendulum-v1", buffer_size=10, learning_starts=10, policy_kwargs={"net_arch": [4]}, device="cpu")
    model.learn(2, callback=checkpoint)
    run = Path(manager.save_path)
    assert sorted(path.name for path in run.iterdir()) == ["rl_model_2_steps.zip", "rl_model_replay_buffer_2_steps.pkl"]


@checks("ExperimentManager._load_pretrained_agent loads replay_buffer.pkl beside -i")
def test_the_zoo_loads_the_replay_buffer_beside_an_i_model_and_ours_then_loads_none(monkeypatch, tmp_path):
    loaded = []

    class Loaded(Model):
        online_fraction = 0.5  # a fine-tuning

        @classmethod
        def load(cls, path, **kwargs):
            return cls()

        def load_replay_buffer(self, path, **kwargs):
            loaded.append(Path(path))

        def learn(self, total_timesteps, **kwargs):
            pass

    run = tmp_path / "run"
    run.mkdir()
    model_path = tiny_sac(run / "rl_model_2_steps")
    (run / "rl_model_replay_buffer_2_steps.pkl").write_bytes(b"")
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "-i", str(model_path))
    monkeypatch.setitem(exp_manager.ALGOS, "cql", Loaded)
    manager.learn(manager._load_pretrained_agent({"policy": "MlpPolicy"}, None))
    assert loaded == [run / "rl_model_replay_buffer_2_steps.pkl"]  # no replay_buffer.pkl: the checkpoint's
    (run / "replay_buffer.pkl").write_bytes(b"")
    loaded.clear()
    manager.learn(manager._load_pretrained_agent({"policy": "MlpPolicy"}, None))
    assert loaded == [run / "replay_buffer.pkl"]  # the zoo's only


@checks("ExperimentManager.read_hyperparameters applies --hyperparams")
@checks("ExperimentManager._preprocess_hyperparams takes env_kwargs from read_hyperparameters")
def test_the_config_env_kwargs_reach_the_evaluation_env_and_its_option_keys_the_manager(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--eval-episodes", "5", "--hyperparams", "save_freq:7")
    hyperparams, saved = manager.read_hyperparameters()
    config = yaml.safe_load(Path(manager.config).read_text())["Panda-v0"]
    assert manager.config == str(hyperparams_dir() / "cql.yml")  # no --conf-file: ours
    assert not set(OPTIONS) & set(hyperparams) and saved["eval_freq"] == config["eval_freq"]
    assert (manager.eval_freq, manager.n_eval_episodes, manager.save_freq) == (config["eval_freq"], 5, 7)  # given: 5
    ZooExperimentManager._preprocess_hyperparams(manager, hyperparams)
    assert manager.env_kwargs == manager.eval_env_kwargs == manager.args.env_kwargs == config["env_kwargs"]

    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--eval-env-kwargs", "action_mode:'absolute'")
    ZooExperimentManager._preprocess_hyperparams(manager, manager.read_hyperparameters()[0])
    assert (manager.env_kwargs, manager.eval_env_kwargs) == (config["env_kwargs"], {"action_mode": "absolute"})


@checks("ExperimentManager._preprocess_schedules reads learning_rate 'lin_<x>'")
def test_the_zoo_reads_the_learning_rate_schedule_and_ours_the_actors(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, "--algo", "iql", "--env", "Panda-v0", "--hyperparams",
                            "learning_rate:'lin_1e-3'", "actor_learning_rate:'lin_2e-3'")  # fmt: skip
    hyperparams, _ = manager.read_hyperparameters()
    assert isinstance(hyperparams["learning_rate"], str) and hyperparams["actor_learning_rate"](0.5) == 1e-3
    hyperparams = ZooExperimentManager._preprocess_hyperparams(manager, hyperparams)[0]
    assert hyperparams["learning_rate"](0.5) == 5e-4


def test_a_conf_file_of_ours_not_in_the_working_folder_is_our_copy(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--conf-file", "cql_finetune.yml")
    assert manager.config == str(hyperparams_dir() / "cql_finetune.yml")
    (tmp_path / "mine.yml").write_text("Panda-v0: {policy: MlpPolicy, n_timesteps: 1}\n")
    assert made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--conf-file", "mine.yml").config == "mine.yml"
    assert made_by_train(monkeypatch, tmp_path, "--algo", "calql", "--env", "Panda-v0").config == str(
        hyperparams_dir() / "cql.yml"
    )


@checks("record_video reads env_kwargs from the args.yml that ExperimentManager._save_config writes")
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
def test_the_run_folder_is_numbered_one_past_the_highest(monkeypatch, tmp_path):
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN)
    assert Path(manager.save_path) == Path("logs", "cql", "Panda-v0_1")
    Path("logs", "cql", "Panda-v0_3").mkdir(parents=True)
    assert Path(made_by_train(monkeypatch, tmp_path, *CQL_RUN).save_path) == Path("logs", "cql", "Panda-v0_4")


@checks("ExperimentManager.setup_experiment calls create_log_folder before it writes")
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


@checks("the zoo makes, loads and saves its models through ALGOS[algo]")
def test_the_zoos_models_are_of_the_class_in_algos_whose_saves_leave_a_file_whole(monkeypatch, tmp_path):
    written = []
    save, save_buffer = SAC.save, SAC.save_replay_buffer
    monkeypatch.setattr(SAC, "save", lambda self, path, *args: written.append(Path(path)) or save(self, path, *args))
    monkeypatch.setattr(SAC, "save_replay_buffer", lambda self, path: written.append(Path(path)) or save_buffer(self, path))
    manager = made_by_train(monkeypatch, tmp_path, "--algo", "sac", "--env", "Pendulum-v1", "-f", "logs", "-n", "2",
                            "--save-freq", "2", "--eval-freq", "2", "--eval-episodes", "1", "--save-replay-buffer",
                            "--hyperparams", "buffer_size:10", "learning_starts:10",
                            "policy_kwargs:dict(net_arch=[4])")  # fmt: skip
    model, _ = ExperimentManager.setup_experiment(manager)
    assert type(model) is exp_manager.ALGOS["sac"] and type(model).__name__ == "SAC" and type(model).saves_atomically
    assert [type(callback) for callback in manager.callbacks] == [CheckpointCallback, EvalCallback]
    manager.learn(model)
    manager.save_trained_model(model)
    run = Path(manager.save_path)
    # Each file written under a temporary name beside its own, then renamed: none is left.
    finals = [re.fullmatch(r"\.(.+)\.\d+-[0-9a-f]{8}\.tmp", path.name)[1] for path in written]
    assert {path.parent for path in written} == {run}
    assert finals == ["rl_model_2_steps.zip", "best_model.zip", "Pendulum-v1.zip", "replay_buffer.pkl"]
    assert sorted(path.name for path in run.iterdir() if path.suffix in (".zip", ".pkl", ".tmp")) == sorted(finals)


@checks("utils.get_callback_list makes a config's callback: entries with their keywords")
@checks("OffPolicyAlgorithm.learn reads action_noise after the callbacks start")
def test_a_configs_exploration_noise_callback_is_the_noise_the_model_explores_with(monkeypatch, tmp_path):
    entry = "callback:[{'sb3_cql.zoo.callbacks.ExplorationNoise': {'pink_std': 0.2, 'hold': 3}}]"
    manager = made_by_train(monkeypatch, tmp_path, *CQL_RUN, "--hyperparams", entry)
    _, _, (callback,), _ = ZooExperimentManager._preprocess_hyperparams(manager, manager.read_hyperparameters()[0])
    assert isinstance(callback, ExplorationNoise) and (callback.pink_std, callback.hold) == (0.2, 3)
    used = []
    model = SAC("MlpPolicy", "Pendulum-v1", learning_starts=10, policy_kwargs={"net_arch": [4]}, seed=1, device="cpu")
    model.action_noise = NormalActionNoise(0.0, 1.0)
    collect = model.collect_rollouts
    monkeypatch.setattr(model, "collect_rollouts", lambda *a, **k: used.append(k["action_noise"]) or collect(*a, **k))
    model.learn(4, callback=callback)
    assert used and all(noise is model.action_noise for noise in used)
    noise = model.action_noise
    assert type(noise).__name__ == "HeldActionNoise" and noise.hold == 3 and type(noise.noise).__name__ == "PinkActionNoise"


@pytest.mark.parametrize("settings", [{"hold": 0}, {"pink_std": -1.0}, {"hold": 2}])
def test_bad_exploration_noise_settings_end_the_run_on_one_line_and_leave_no_run_folder(monkeypatch, tmp_path, settings,
                                                                                        capsys):  # fmt: skip
    entry = f"callback:[{{'sb3_cql.zoo.callbacks.ExplorationNoise': {settings!r}}}]"  # hold 2: of no noise
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["train", "--algo", "sac", "--env", "Pendulum-v1", "-f", "logs", "-n", "1",
                                      "--eval-freq", "-1", "--hyperparams", "buffer_size:10", entry])  # fmt: skip
    with pytest.raises(SystemExit) as ended:
        train.train()
    assert ended.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("python -m rl_zoo3.train: error: ExplorationNoise") and ("noise" in line or "hold" in line)
    assert not list(tmp_path.rglob("Pendulum-v1_*"))


@checks("ExperimentManager.objective calls the sampler with (trial, n_actions, n_envs, additional_args)")
def test_tuning_samples_cql_with_the_zoos_arguments_and_reads_a_trial_back_with_our_converter(monkeypatch, tmp_path):
    from sb3_cql.zoo.search_space import convert_params, sample_cql_params

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
    assert manager.load_trial(storage, "cql", trial_id=0) == convert_params(trial.params)


@checks("train.py reads --hyperparams and --env-kwargs with utils.StoreDict")
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


def test_every_behaviour_in_zoo_internals_has_its_check():
    behaviours = {internal.name for internal in of_kind("behaviour")}
    assert set(BEHAVIOURS_CHECKED) == behaviours, (
        f"without a check: {sorted(behaviours - set(BEHAVIOURS_CHECKED))}; "
        f"checked but not in ZOO_INTERNALS: {sorted(set(BEHAVIOURS_CHECKED) - behaviours)}"
    )
    assert {internal.kind for internal in ZOO_INTERNALS} == {"method", "attribute", "option", "behaviour"}
    assert all(internal.reason for internal in ZOO_INTERNALS)
    assert len({internal.name for internal in ZOO_INTERNALS}) == len(ZOO_INTERNALS)
