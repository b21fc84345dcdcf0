"""RL-Zoo3 integration, through the zoo's own command lines in fresh interpreters, as users run them."""

import configparser
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml
from rollouts import TINY_PANDA_COLLECT
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_cql import CQL
from sb3_cql.common.atomic import saved_model_problem

# Tiny networks and batches: the point is the plumbing, not the learning.
TINY = ["--hyperparams", "batch_size:64", "policy_kwargs:dict(net_arch=[32, 32])"]


class Zoo:
    """A working folder whose datasets folder holds a 4-episode ``sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0``, our configs'."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.env = {**os.environ, "MINARI_DATASETS_PATH": str(root / "datasets"), "MPLBACKEND": "Agg"}

    def run(self, *args: str, module: str | None = "rl_zoo3.train", timeout: float = 600) -> str:
        result = self.attempt(*args, module=module, timeout=timeout)
        assert result.returncode == 0, f"{result.args} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
        return result.stdout

    def attempt(self, *args: str, module: str | None = "rl_zoo3.train", timeout: float = 600) -> subprocess.CompletedProcess:
        command = [sys.executable, "-m", module, *args] if module else list(args)
        return subprocess.run(command, cwd=self.root, env=self.env, capture_output=True, text=True, timeout=timeout)

    def python(self, code: str) -> str:
        return self.run(sys.executable, "-c", code, module=None).strip().splitlines()[-1]


@pytest.fixture(scope="module")
def zoo(tmp_path_factory) -> Zoo:
    zoo = Zoo(tmp_path_factory.mktemp("zoo"))
    zoo.run(*TINY_PANDA_COLLECT, module="sb3_cql.data")
    return zoo


@pytest.fixture(scope="module")
def trained(zoo) -> Path:
    """A zoo training of 200 gradient steps, evaluated every 100 (command-line values over the config's); its output
    is kept in ``train_output.txt`` beside the logs."""
    output = zoo.run("--algo", "cql", "--env", "Panda-v0", "-n", "200", "--eval-freq", "100", "--eval-episodes", "2",
                     "-f", "logs", "-tb", "tb", "--seed", "0", *TINY)  # fmt: skip
    (zoo.root / "train_output.txt").write_text(output)
    return zoo.root / "logs" / "cql" / "Panda-v0_1"


def interrupt(zoo: Zoo, args: list[str], ready: Callable[[], bool], env: dict[str, str] | None = None):
    """Run ``rl_zoo3.train ARGS`` as a real process, send it SIGINT (Ctrl-C) once ``ready()``, and return it ended,
    with its output."""
    process = subprocess.Popen([sys.executable, "-m", "rl_zoo3.train", *args], cwd=zoo.root, env=env or zoo.env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.monotonic() + 300
    while not ready() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert process.poll() is None, f"ended before it could be interrupted:\n{process.communicate()}"
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=300)
    return process.returncode, stdout, stderr


def python_in_fresh_interpreter(code: str) -> str:
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return result.stdout.strip().splitlines()[-1]


def test_start_up_imports_neither_torch_nor_the_zoo():
    code = "import sys; print([name for name in ('torch', 'rl_zoo3', 'stable_baselines3') if name in sys.modules])"
    assert python_in_fresh_interpreter(code) == "[]"
    code = "import sys; print([type(finder).__name__ for finder in sys.meta_path if type(finder).__name__ == 'ZooImportHook'])"
    assert python_in_fresh_interpreter(code) == "['ZooImportHook']"  # the installed .pth put the hook in place


def test_importing_the_zoo_registers_cql_the_tasks_and_the_search_space():
    code = (
        "import gymnasium; from rl_zoo3 import ALGOS; from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER; "
        "print(ALGOS['cql'].__module__, 'cql' in HYPERPARAMS_SAMPLER, 'PandaPerturbed-v0' in gymnasium.registry)"
    )
    assert python_in_fresh_interpreter(code) == "sb3_cql.cql.cql True True"


def test_importing_the_plugin_by_hand_extends_a_zoo_loaded_without_the_hook():
    code = (
        "import sys; sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != 'ZooImportHook']; "
        "from rl_zoo3 import ALGOS; before = 'cql' in ALGOS; import sb3_cql.zoo.plugin; print(before, 'cql' in ALGOS)"
    )
    assert python_in_fresh_interpreter(code) == "False True"


def test_zoo_training_logs_evaluations_tensorboard_and_checkpoints(trained):
    evaluations = np.load(trained / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [100, 200]
    assert evaluations["results"].shape == (2, 2) and evaluations["successes"].shape == (2, 2)
    assert (trained / "best_model.zip").is_file() and (trained / "Panda-v0.zip").is_file()
    config = yaml.unsafe_load((trained / "Panda-v0" / "config.yml").read_text())
    # hyperparams/cql.yml, found without --conf-file
    assert dict(config)["dataset"] == "sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0"
    # the config's fixed conservative weight reaches the model, not the constructor's learned one
    model = CQL.load(trained / "Panda-v0.zip")
    assert (model.cql_alpha, model.cql_target_action_gap, model.alpha_prime_optimizer) == (10.0, None, None)

    (events,) = (trained.parents[2] / "tb" / "Panda-v0").glob("CQL_1/events.out.tfevents.*")
    tags = EventAccumulator(str(events)).Reload().Tags()["scalars"]
    for tag in ("train/critic_loss", "train/actor_loss", "train/cql_loss", "train/cql_q_data", "train/cql_q_random",
                "train/cql_q_policy", "eval/success_rate", "eval/mean_reward"):  # fmt: skip
        assert tag in tags, tag


def test_fine_tuning_online_explores_around_its_action_checkpoints_its_transitions_and_continues_from_them(zoo, trained):
    finetune = ["--algo", "cql", "--env", "PandaForce-v0", "--conf-file", "cql_finetune.yml", "-f", "finetune"]
    zoo.run(*finetune, "-i", str(trained / "Panda-v0.zip"), "-n", "300", "--eval-freq", "150", "--eval-episodes", "1",
            "--save-freq", "150", "-tb", "tb", "--seed", "0")  # fmt: skip
    run = zoo.root / "finetune" / "cql" / "PandaForce-v0_1"
    assert np.load(run / "evaluations.npz")["timesteps"].tolist() == [150, 300]  # env steps
    (events,) = (zoo.root / "tb" / "PandaForce-v0").glob("CQL_1/events.out.tfevents.*")
    assert "eval/success_rate" in EventAccumulator(str(events)).Reload().Tags()["scalars"]
    assert (run / "rl_model_replay_buffer_150_steps.pkl").is_file()
    # The config acts with the deterministic action plus N(0, 0.1) noise, not with samples of the policy.
    acting = "from sb3_cql import CQL; m = CQL.load('{}'); print(m.deterministic_rollouts, m.action_noise)"
    deterministic, noise = zoo.python(acting.format(run / "PandaForce-v0.zip")).split(" ", 1)
    assert deterministic == "True" and noise.startswith("NormalActionNoise(mu=[0. 0. 0. 0. 0. 0. 0. 0. 0.]")
    assert noise.endswith("sigma=[0.1 0.1 0.1 0.1 0.1 0.1 0.1 0.1 0.1])")
    online_size = ("from sb3_cql import CQL; m = CQL.load('{}'); m.load_replay_buffer('{}'); "
                   "print(m.replay_buffer.online.size())")  # fmt: skip
    # A checkpoint is saved before its step's transition is stored.
    assert zoo.python(online_size.format(run / "PandaForce-v0.zip", run / "rl_model_replay_buffer_300_steps.pkl")) == "299"

    output = zoo.run(*finetune, "-i", str(run / "rl_model_150_steps.zip"), "-n", "100", "--eval-freq", "-1",
                     "--save-replay-buffer")  # fmt: skip
    assert f"Loading the replay buffer of the checkpoint: {run / 'rl_model_replay_buffer_150_steps.pkl'}" in output
    resumed = zoo.root / "finetune" / "cql" / "PandaForce-v0_2"
    assert zoo.python(online_size.format(resumed / "PandaForce-v0.zip", resumed / "replay_buffer.pkl")) == "249"

    # A model of another action mode: SB3's own check refuses it, and the run leaves no folder without a model.
    mismatch = zoo.attempt(*finetune, "-i", str(trained / "Panda-v0.zip"), "--env-kwargs", "action_mode:'absolute'")
    assert mismatch.returncode != 0 and "Action spaces do not match" in mismatch.stderr
    assert not (zoo.root / "finetune" / "cql" / "PandaForce-v0_3").exists()


def test_ctrl_c_during_training_keeps_the_model_at_that_step(zoo):
    """The zoo's own Ctrl-C: it saves the model as it is, whole, beside the best evaluated so far."""
    run = zoo.root / "logs" / "bc" / "Panda-v0_1"
    status, stdout, stderr = interrupt(
        zoo, ["--algo", "bc", "--env", "Panda-v0", "-n", "1000000", "--eval-freq", "50", "--eval-episodes", "1",
              "-f", "logs", *TINY], ready=lambda: (run / "best_model.zip").is_file())  # fmt: skip
    assert status == 0 and "Traceback" not in stderr
    assert stdout.strip().splitlines()[-1] == f"Saving to {run.relative_to(zoo.root)}"
    from sb3_cql import BC

    assert saved_model_problem(run / "Panda-v0.zip") is None and saved_model_problem(run / "best_model.zip") is None
    assert 50 <= BC.load(run / "Panda-v0.zip").num_timesteps < 1000000


def test_ctrl_c_while_the_dataset_is_collected_leaves_no_run_folder(zoo):
    # An empty datasets folder: the run collects its config's standard dataset (1,000 episodes) first.
    env = {**zoo.env, "MINARI_DATASETS_PATH": str(zoo.root / "empty-datasets")}
    logs = zoo.root / "logs-interrupted"
    status, stdout, stderr = interrupt(
        zoo, ["--algo", "cql", "--env", "Panda-v0", "-f", str(logs), *TINY],
        ready=lambda: any((zoo.root / "empty-datasets").rglob("*.pkl")), env=env)  # fmt: skip
    assert status == 130 and "Traceback" not in stderr
    last_line = stderr.strip().splitlines()[-1]
    assert last_line.startswith("interrupted: ") and "episodes of sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0 kept" in last_line
    assert not list(logs.glob("cql/Panda-v0_*"))  # the next run is Panda-v0_1 again


def test_enjoy_record_video_and_plots_work_on_the_trained_model(zoo, trained):
    assert "Loading" in zoo.run("--algo", "cql", "--env", "Panda-v0", "-f", "logs", "--exp-id", "1", "-n", "20",
                                "--no-render", module="rl_zoo3.enjoy")  # fmt: skip
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-f", "logs", "--exp-id", "1", "-n", "10", "-o", "videos",
            module="rl_zoo3.record_video")  # fmt: skip
    assert list((zoo.root / "videos").glob("*.mp4"))
    zoo.run("-a", "cql", "-e", "Panda-v0", "-f", "logs/", "--no-display", "-o", "plots", "-k", "successes",
            module="rl_zoo3.plots.all_plots")  # fmt: skip
    assert (zoo.root / "plots.pkl").is_file()


def test_a_chunked_model_trains_evaluates_plays_and_records_through_the_zoo(zoo):
    """Action chunks through every zoo entry point: the chunk length from the command line, then read from the model."""
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-n", "30", "--eval-freq", "15", "--eval-episodes", "1", "-f", "chunked",
            "--seed", "0", *TINY, "action_chunk:3", "cql_n_actions:2")  # fmt: skip
    model = zoo.root / "chunked" / "cql" / "Panda-v0_1" / "Panda-v0.zip"
    assert zoo.python(f"from sb3_cql import CQL; print(CQL.load('{model}').policy.action_chunk)") == "3"
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-f", "chunked", "--exp-id", "1", "-n", "12", "--no-render",
            module="rl_zoo3.enjoy")  # fmt: skip
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-f", "chunked", "--exp-id", "1", "-n", "10", "-o", "chunked_videos",
            module="rl_zoo3.record_video")  # fmt: skip
    assert list((zoo.root / "chunked_videos").glob("*.mp4"))
    assert "Panda-v0" in zoo.run(str(model), "--algo", "cql", "-n", "1", "--env", "Panda-v0", module="sb3_cql.evaluate")


def test_a_chunked_model_fine_tunes_with_the_chunked_config_and_continues_from_a_checkpoint(zoo):
    """cql_finetune_chunked.yml, below --hyperparams: one gradient step and one decision per chunk, pink noise (the
    config's callback) seeded by the run's seed; the online transitions keep single steps, sampled as chunks, and a
    checkpoint continues with them."""
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-n", "20", "--eval-freq", "-1", "-f", "chunked-offline", "--seed", "0",
            *TINY, "action_chunk:5", "cql_n_actions:2")  # fmt: skip
    offline = zoo.root / "chunked-offline" / "cql" / "Panda-v0_1" / "Panda-v0.zip"
    finetune = ["--algo", "cql", "--env", "PandaForce-v0", "--conf-file", "cql_finetune_chunked.yml", "-f",
                "chunked-finetune", "--eval-episodes", "1", "--seed", "3"]  # fmt: skip
    output = zoo.run(*finetune, "-i", str(offline), "-n", "100", "--eval-freq", "50", "--save-freq", "50",
                     "--hyperparams", "gradient_steps:2")  # fmt: skip
    assert "Applying pink noise with std 0.1 (sequences of 700 steps)" in output
    run = zoo.root / "chunked-finetune" / "cql" / "PandaForce-v0_1"
    config = dict(yaml.unsafe_load((run / "PandaForce-v0" / "config.yml").read_text()))
    assert (config["train_freq"], config["gradient_steps"]) == (5, 2)  # --hyperparams win
    assert config["callback"] == [{"sb3_cql.zoo.callbacks.ExplorationNoise": {"pink_std": 0.1}}]
    check = ("from sb3_cql import CQL; m = CQL.load('{}'); m.load_replay_buffer('{}'); o = m.replay_buffer.online; "
             "print(m.train_freq.frequency, m._n_updates, type(m.action_noise).__name__, o.size(), "
             "o.sample(4).actions.shape[1], o.single_step_samples(4).actions.shape[1])")  # fmt: skip
    assert zoo.python(check.format(run / "PandaForce-v0.zip", run / "rl_model_replay_buffer_100_steps.pkl")).split() == [
        "5",
        "60",
        "PinkActionNoise",
        "99",
        "45",
        "9",
    ]  # fmt: skip  (20 offline steps, then 20 trainings of 2 in 100 env steps)
    output = zoo.run(*finetune, "-i", str(run / "rl_model_50_steps.zip"), "-n", "50", "--eval-freq", "-1",
                     "--save-replay-buffer")  # fmt: skip
    assert f"Loading the replay buffer of the checkpoint: {run / 'rl_model_replay_buffer_50_steps.pkl'}" in output
    resumed = zoo.root / "chunked-finetune" / "cql" / "PandaForce-v0_2"
    assert zoo.python(check.format(resumed / "PandaForce-v0.zip", resumed / "replay_buffer.pkl")).split()[3] == "99"


def test_evaluation_settings_come_from_the_config(zoo):
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-n", "150", "-f", "config-eval", *TINY,
            "eval_freq:75", "n_eval_episodes:1")  # fmt: skip
    evaluations = np.load(zoo.root / "config-eval" / "cql" / "Panda-v0_1" / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [75, 150] and evaluations["results"].shape == (2, 1)
    # A command-line value wins over the config even when it is the zoo's default (5 episodes).
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-n", "75", "-f", "explicit-eval", *TINY, "eval_freq:75",
            "n_eval_episodes:1", "--eval-episodes", "5")  # fmt: skip
    evaluations = np.load(zoo.root / "explicit-eval" / "cql" / "Panda-v0_1" / "evaluations.npz")
    assert evaluations["results"].shape == (1, 5)


def test_env_kwargs_of_the_config_reach_the_evaluation_env(zoo):
    zoo.run("collect", "--episodes", "2", "--action-mode", "delta", module="sb3_cql.data")  # sb3cql/Panda-v0/pid-delta-v0
    (zoo.root / "delta.yml").write_text(
        "Panda-v0:\n  policy: MlpPolicy\n  n_timesteps: 4\n  dataset: sb3cql/Panda-v0/pid-delta-v0\n"
        "  env_kwargs:\n    action_mode: delta\n  batch_size: 16\n  policy_kwargs: 'dict(net_arch=[8])'\n"
    )
    # Record the action bound of the training and evaluation envs the zoo makes (1 in delta mode, the joint limits else).
    code = (
        "import sys; from rl_zoo3 import train; from rl_zoo3.exp_manager import ExperimentManager; bounds = {}\n"
        "create = ExperimentManager.create_envs\n"
        "def recording(self, n_envs, eval_env=False, no_log=False):\n"
        "    envs = create(self, n_envs, eval_env, no_log); bounds[eval_env] = float(envs.action_space.high.max())\n"
        "    return envs\n"
        "ExperimentManager.create_envs = recording\n"
        "sys.argv = ['train', '--algo', 'cql', '--env', 'Panda-v0', '-n', '4', '--eval-freq', '2', '--eval-episodes', '1',"
        " '-f', 'delta', '--conf-file', 'delta.yml']\n"
        "train.train(); print(sorted(bounds.items()))"
    )
    assert zoo.python(code) == "[(False, 1.0), (True, 1.0)]"


def test_console_script_with_an_explicit_config_file(zoo):
    rl_zoo3 = shutil.which("rl_zoo3")
    assert rl_zoo3 is not None
    (zoo.root / "mine.yml").write_text(
        "Panda-v0:\n  policy: MlpPolicy\n  n_timesteps: 20\n  dataset: sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0\n"
        "  batch_size: 16\n"
        "  env_kwargs: {action_mode: delta}\n  policy_kwargs: 'dict(net_arch=[8])'\n"
    )
    zoo.run(rl_zoo3, "train", "--algo", "cql", "--env", "Panda-v0", "-n", "20", "--eval-freq", "-1", "-f", "mine",
            "--conf-file", "mine.yml", module=None)  # fmt: skip
    config = dict(yaml.unsafe_load((zoo.root / "mine" / "cql" / "Panda-v0_1" / "Panda-v0" / "config.yml").read_text()))
    assert config["batch_size"] == 16 and "eval_freq" not in config  # mine.yml, not hyperparams/cql.yml


def test_every_config_file_is_installed_with_the_package():
    root = Path(__file__).resolve().parents[1]
    setup = configparser.ConfigParser()
    setup.read(root / "setup.cfg")
    installed = {Path(name.strip()).name for name in setup["options.data_files"]["share/sb3-cql/hyperparams"].split(",")}
    assert installed == {path.name for path in (root / "hyperparams").glob("*.yml")}


def test_sac_baseline_starts_from_the_dataset(zoo):
    output = zoo.run("--algo", "sac", "--env", "Panda-v0", "-n", "30", "--eval-freq", "-1", "-f", "sac", *TINY,
                     "learning_starts:10", "callback:[{'sb3_cql.callbacks.PrefillReplayBuffer': "
                     "{'dataset': 'sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0', 'verbose': 1}}]")  # fmt: skip
    size = zoo.python(
        "from sb3_cql.data import load_dataset; print(load_dataset('sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0').total_steps)"
    )
    assert f"Replay buffer: {size} transitions from sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0" in output


def test_tuning_with_sqlite_storage(zoo):
    storage = f"sqlite:///{zoo.root / 'study.db'}"
    # A seeded sampler: the same two trials (their networks, batches and sampled actions) at every run.
    zoo.run("--algo", "cql", "--env", "Panda-v0", "-n", "40", "--eval-episodes", "1", "-optimize", "--n-trials", "2",
            "--n-evaluations", "1", "--storage", storage, "--study-name", "cql", "-f", "tuning", "--no-optim-plots",
            "--seed", "0", "--hyperparams", "policy_kwargs:dict(net_arch=[8])")  # fmt: skip
    trials = optuna.load_study(study_name="cql", storage=storage).get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 2
    for trial in trials:
        sampled = {"cql_alpha", "learning_rate", "actor_learning_rate", "batch_size", "cql_n_actions", "net_arch",
                   "bc_steps", "actor_bc_weight", "reward", "n_steps"}  # fmt: skip
        sampled |= {"bc_learning_rate"} if trial.params["bc_steps"] > 0 else set()
        assert set(trial.params) == sampled


@pytest.mark.parametrize("bc_steps", [0, 5000])
def test_the_search_space_samples_a_warm_start_learning_rate_only_for_a_warm_start(bc_steps):
    from sb3_cql.zoo.search_space import sample_cql_params

    raw = {"cql_alpha": 5.0, "learning_rate": 3e-4, "actor_learning_rate": 3e-5, "batch_size": 352,
           "cql_n_actions": 10, "net_arch": "large", "bc_steps": bc_steps, "bc_learning_rate": 1e-3,
           "actor_bc_weight": 0.4, "reward": "shifted", "n_steps": 5}  # fmt: skip
    params = sample_cql_params(optuna.trial.FixedTrial(raw), n_actions=9, n_envs=1, additional_args={})
    assert params["bc_steps"] == bc_steps and params["actor_bc_weight"] == 0.4
    assert params["n_steps"] == 5
    assert (params["reward_scale"], params["reward_bias"]) == (4.0, -2.0) and "reward" not in params
    assert params["policy_kwargs"] == {"net_arch": [256, 256, 256]}
    assert ("bc_learning_rate" in params) == (bc_steps > 0)


@pytest.mark.slow
def test_tuning_processes_share_a_postgresql_study(zoo, postgres_url):
    optuna.create_study(storage=postgres_url, study_name="cql", direction="maximize")
    args = ["--algo", "cql", "--env", "Panda-v0", "-n", "40", "--eval-episodes", "1", "-optimize", "--n-trials", "2",
            "--n-evaluations", "1", "--storage", postgres_url, "--study-name", "cql", "--no-optim-plots",
            "--hyperparams", "policy_kwargs:dict(net_arch=[8])"]  # fmt: skip
    workers = [
        subprocess.Popen(
            [sys.executable, "-m", "rl_zoo3.train", *args, "-f", f"worker{i}"],
            cwd=zoo.root,
            env=zoo.env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        for i in range(2)
    ]
    assert [worker.wait(timeout=600) for worker in workers] == [0, 0]
    trials = optuna.load_study(study_name="cql", storage=postgres_url).get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 4


def test_a_model_trained_on_one_task_is_evaluated_on_the_others(zoo, trained):
    output = zoo.run(str(trained / "best_model.zip"), "--algo", "cql", "--env", "PandaForce-v0", "PandaPerturbed-v0",
                     "-n", "1", module="sb3_cql.evaluate")  # fmt: skip
    lines = [line for line in output.splitlines() if "success rate" in line]
    assert [line.split(":")[0] for line in lines] == ["PandaForce-v0", "PandaPerturbed-v0"]


def test_evaluation_is_deterministic_given_the_seed():
    from sb3_cql.evaluate import load_policy, success_rate

    controller = load_policy("pid", None, "PandaPerturbed-v0")
    first, again = (success_rate(controller, "PandaPerturbed-v0", n_episodes=4, seed=3) for _ in range(2))
    assert first == again
    assert success_rate(controller, "Panda-v0", n_episodes=2, seed=0) == 1.0
    with pytest.raises(ValueError, match="unknown algo"):
        load_policy("model.zip", "nothing", "Panda-v0")


def test_the_pd_controller_is_evaluated_in_the_action_mode_given(capsys):
    from sb3_cql.evaluate import main

    main(["pid", "--env", "Panda-v0", "-n", "2", "--env-kwargs", "action_mode:'delta'"])
    assert "Panda-v0: success rate 1.000 over 2 episodes" in capsys.readouterr().out
    with pytest.raises(SystemExit) as error:
        main(["pid", "--env", "Panda-v0", "-n", "1", "--env-kwargs", "action_mode:'velocity'"])
    assert error.value.code == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("python -m sb3_cql.evaluate: error: pid on Panda-v0:") and "action_mode" in line


@pytest.mark.parametrize("items", [["action_mode:'delta'", "model.zip"], ["action_mode:delta"]])
def test_env_kwargs_that_are_not_key_value_items_are_a_usage_error(capsys, items):
    from sb3_cql.evaluate import main

    with pytest.raises(SystemExit) as error:
        main(["pid", "--env", "Panda-v0", "--env-kwargs", *items])
    assert error.value.code == 2
    assert f"--env-kwargs takes KEY:VALUE items with a Python value (e.g. action_mode:\"'delta'\"), got {items[-1]!r}" in (
        capsys.readouterr().err
    )


def test_pid_regrasp_names_the_regrasping_pd_controller():
    from sb3_cql.evaluate import load_policy

    assert load_policy("pid-regrasp", None, "PandaForce-v0").regrasp
    assert not load_policy("pid", None, "PandaForce-v0").regrasp


#: ``python -m rl_zoo3.train`` with ``sys.argv[3:]``, which waits once it has numbered its run (``__init__``) until
#: ``sys.argv[2]`` runs have, each leaving a file in the folder ``sys.argv[1]``: all of them then make their run
#: folders at the same moment.
TOGETHER = """
import os, sys, time
from pathlib import Path
from rl_zoo3 import train
from rl_zoo3.exp_manager import ExperimentManager

barrier, runs = Path(sys.argv[1]), int(sys.argv[2])
setup_experiment = ExperimentManager.setup_experiment

def together(self):
    (barrier / str(os.getpid())).touch()
    while len(list(barrier.iterdir())) < runs:
        time.sleep(0.01)
    return setup_experiment(self)

ExperimentManager.setup_experiment = together
sys.argv = ["train", *sys.argv[3:]]
train.train()
"""


@pytest.mark.parametrize("algo", ["bc", "sac"])
def test_runs_started_together_take_a_folder_each_and_say_where_their_own_models_are(zoo, algo):
    barrier = zoo.root / f"numbered-{algo}"
    barrier.mkdir()
    args = ["--algo", algo, "--env", "Panda-v0", "-n", "20", "--eval-freq", "-1", "-f", "two runs", *TINY,
            "buffer_size:10000"]  # fmt: skip
    runs = [subprocess.Popen([sys.executable, "-c", TOGETHER, str(barrier), "2", *args], cwd=zoo.root, env=zoo.env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]  # fmt: skip
    outputs = [run.communicate(timeout=600) for run in runs]
    assert [run.returncode for run in runs] == [0, 0], [stderr[-3000:] for _, stderr in outputs]
    folders = [f"two runs/{algo}/Panda-v0_1", f"two runs/{algo}/Panda-v0_2"]
    assert sorted(str(path.relative_to(zoo.root)) for path in (zoo.root / "two runs" / algo).iterdir()) == folders
    saved = [re.findall(r"^Saving to (.+)$", stdout, re.MULTILINE) for stdout, _ in outputs]
    assert sorted(saved) == [[folder] for folder in folders]  # each run its own folder
    for folder in folders:
        assert saved_model_problem(zoo.root / folder / "Panda-v0.zip") is None
        config = yaml.unsafe_load((zoo.root / folder / "Panda-v0" / "config.yml").read_text())
        assert config["buffer_size"] == 10000 and (zoo.root / folder / "0.monitor.csv").is_file()


#: ``python -m rl_zoo3.train`` with ``sys.argv[1:]``, whose save of the checkpoint of step 20 writes half its file
#: (SB3's own writer, into the file SB3 would write) and waits (on stdin) to be killed.
CUT_SHORT_CHECKPOINT = """
import io, sys
from stable_baselines3.common import base_class, save_util
from rl_zoo3 import train

whole_save = base_class.save_to_zip_file

def cut_short(path, *args, **kwargs):
    if "rl_model_20_steps" not in str(path):
        return whole_save(path, *args, **kwargs)
    whole = io.BytesIO()
    whole_save(whole, *args, **kwargs)
    with save_util.open_path(path, "w", suffix="zip") as file:
        file.write(whole.getvalue()[: len(whole.getvalue()) // 2])
        file.flush()
    print("half written", flush=True)
    sys.stdin.read()

base_class.save_to_zip_file = cut_short
sys.argv = ["train", *sys.argv[1:]]
train.train()
"""


def test_a_kill_during_a_checkpoint_save_of_sb3s_sac_leaves_every_checkpoint_whole(zoo):
    args = ["--algo", "sac", "--env", "Panda-v0", "-n", "40", "--save-freq", "10", "--eval-freq", "-1", "-f", "killed",
            *TINY, "buffer_size:10000"]  # fmt: skip
    run = subprocess.Popen([sys.executable, "-c", CUT_SHORT_CHECKPOINT, *args], cwd=zoo.root, env=zoo.env,
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # fmt: skip
    try:
        assert "half written\n" in iter(run.stdout.readline, ""), "the checkpoint of step 20 was never saved"
    finally:
        run.kill()  # SIGKILL, mid-write
        run.wait()
    folder = zoo.root / "killed" / "sac" / "Panda-v0_1"
    assert sorted(path.name for path in folder.glob("*.zip")) == ["rl_model_10_steps.zip"]
    assert saved_model_problem(folder / "rl_model_10_steps.zip") is None
    (partial,) = folder.glob(".rl_model_20_steps.zip.*.tmp")  # what the kill cut short, under a name of its own
    assert partial.stat().st_size > 0


@pytest.fixture(scope="module")
def checkpoints(zoo) -> Path:
    """A BC run with checkpoints at steps 10 and 20."""
    zoo.run("--algo", "bc", "--env", "Panda-v0", "-n", "20", "--save-freq", "10", "--eval-freq", "-1", "-f",
            "checkpointed", *TINY)  # fmt: skip
    return Path("checkpointed", "bc", "Panda-v0_1")


def ended_on_one_line(result: subprocess.CompletedProcess) -> str:
    """The one error line of a zoo run that ended with status 2, without a traceback."""
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    errors = [line for line in result.stderr.splitlines() if line.startswith("python -m rl_zoo3.train: error: ")]
    assert len(errors) == 1 and result.stderr.strip().splitlines()[-1] == errors[0], result.stderr[-3000:]
    return errors[0].removeprefix("python -m rl_zoo3.train: error: ")


@pytest.mark.parametrize(("damage", "problem"), [("empty", "it is empty (0 bytes)"),
                                                 ("truncated", "it is truncated (not a whole zip archive)")])  # fmt: skip
def test_a_damaged_i_checkpoint_ends_the_run_on_one_line_naming_the_fix(zoo, checkpoints, damage, problem):
    damaged = checkpoints / "rl_model_30_steps.zip"  # a copy cut short: the zoo's saves leave a file whole
    whole = (zoo.root / checkpoints / "rl_model_20_steps.zip").read_bytes()
    (zoo.root / damaged).write_bytes(b"" if damage == "empty" else whole[:1000])
    result = zoo.attempt("--algo", "bc", "--env", "Panda-v0", "-n", "10", "--eval-freq", "-1", "-f", f"resumed-{damage}",
                         "-i", str(damaged), *TINY)  # fmt: skip
    assert ended_on_one_line(result) == f"{damaged} cannot be loaded: {problem}; continue from a checkpoint beside it"
    assert not list((zoo.root / f"resumed-{damage}").rglob("Panda-v0_*"))


@pytest.mark.parametrize(
    ("algo", "setting", "message"),
    [
        ("cql", "gamma:1.5", "gamma must be in (0, 1], got 1.5"),
        ("cql", "bc_steps:-3", "bc_steps must be an integer >= 0, got -3"),
        ("bc", "batch_size:0", "batch_size must be an integer >= 1, got 0"),
        ("cql", "dataset:'sb3cql/Panda-v0/none-v0'", "dataset sb3cql/Panda-v0/none-v0 "),
    ],
)
def test_a_bad_setting_or_dataset_ends_the_run_on_one_line_and_leaves_no_run_folder(zoo, algo, setting, message):
    result = zoo.attempt("--algo", algo, "--env", "Panda-v0", "-n", "10", "--eval-freq", "-1", "-f", "refused", *TINY,
                         setting)  # fmt: skip
    assert message in ended_on_one_line(result)
    assert not list((zoo.root / "refused").rglob("Panda-v0_*"))


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("gamma:1.5", "gamma must be in (0, 1], got 1.5"),  # given to SB3's load
        ("dataset:'sb3cql/Panda-v0/none-v0'", "dataset sb3cql/Panda-v0/none-v0 "),  # loaded when training starts
    ],
)
def test_a_fine_tuning_with_a_bad_setting_or_dataset_ends_on_one_line_and_leaves_no_run_folder(zoo, trained, setting, message):
    finetune = ["--algo", "cql", "--env", "PandaForce-v0", "--conf-file", "cql_finetune.yml", "-f", "refused-ft"]
    result = zoo.attempt(*finetune, "-i", str(trained / "Panda-v0.zip"), "-n", "10", "--eval-freq", "-1",
                         "--hyperparams", setting)  # fmt: skip
    assert message in ended_on_one_line(result)
    assert not list((zoo.root / "refused-ft").rglob("PandaForce-v0_*"))


def test_iql_with_best_of_n_trains_plays_and_evaluates_through_the_zoo_acting_by_ranking(zoo):
    """``--algo iql`` with ``best_of_n``, the DDPG+AWR actor and a linear schedule of the actor's own from the command
    line: the model saves them (the actor's rate decayed from 1e-3 over the 30 steps, the critics' constant), and enjoy
    and evaluate act with best-of-N."""
    zoo.run("--algo", "iql", "--env", "Panda-v0", "-n", "30", "--eval-freq", "15", "--eval-episodes", "1", "-f", "iql",
            "--seed", "0", *TINY, "best_of_n:4", "actor_loss_type:'ddpg_awr'", "actor_learning_rate:'lin_1e-3'")  # fmt: skip
    model = zoo.root / "iql" / "iql" / "Panda-v0_1" / "Panda-v0.zip"
    code = (f"from sb3_cql import IQL; m = IQL.load('{model}'); rate = lambda o: o.param_groups[0]['lr']; "
            "print(m.policy.best_of_n, m.gamma, m.actor_loss_type, m.actor_lr_schedule(0.5), "
            "rate(m.actor.optimizer) < 1e-4, rate(m.critic.optimizer) == m.lr_schedule(0.5))")  # fmt: skip
    assert zoo.python(code) == "4 0.999 ddpg_awr 0.0005 True True"
    zoo.run("--algo", "iql", "--env", "Panda-v0", "-f", "iql", "--exp-id", "1", "-n", "12", "--no-render",
            module="rl_zoo3.enjoy")  # fmt: skip
    assert "Panda-v0" in zoo.run(str(model), "--algo", "iql", "-n", "1", "--env", "Panda-v0", module="sb3_cql.evaluate")


def test_the_iql_search_space_gives_iql_keywords():
    from sb3_cql import IQL
    from sb3_cql.zoo.search_space import sample_iql_params

    raw = {"expectile": 0.9, "temperature": 10.0, "gamma": 0.999, "learning_rate": 3e-4, "batch_size": 256,
           "net_arch": "medium", "reward": "data", "n_steps": 5, "best_of_n": 32, "q_agg": "mean",
           "actor_loss_type": "awr"}  # fmt: skip
    params = sample_iql_params(optuna.trial.FixedTrial(raw), n_actions=9, n_envs=1, additional_args={})
    assert params["policy_kwargs"] == {"net_arch": [256, 256]}
    assert (params["reward_scale"], params["reward_bias"]) == (1.0, 0.0)
    assert "actor_bc_weight" not in params  # AWR has no anchor
    IQL("MlpPolicy", "Pendulum-v1", **{**params, "policy_kwargs": {"net_arch": [8]}})  # every key is IQL's
    anchored = {**raw, "actor_loss_type": "ddpg_awr", "actor_bc_weight": 4.0}
    params = sample_iql_params(optuna.trial.FixedTrial(anchored), n_actions=9, n_envs=1, additional_args={})
    assert (params["actor_loss_type"], params["actor_bc_weight"]) == ("ddpg_awr", 4.0)
    IQL("MlpPolicy", "Pendulum-v1", **{**params, "policy_kwargs": {"net_arch": [8]}})
