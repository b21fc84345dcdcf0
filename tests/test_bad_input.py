"""Bad input to each entry point (the command lines, the zoo, the Python API): refused before any work on one line
that says what to type instead (status 2 for a command line), with nothing written and nothing left that blocks the
corrected command; or, where the input is good, done."""

import contextlib
import http.server
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import minari
import numpy as np
import pytest
from minari import MinariDataset
from minari.data_collector import EpisodeBuffer
from minari.dataset.minari_storage import MinariStorage
from rl_zoo3 import train
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.envs import FakeImageEnv

from envs.config import ConfigError
from sb3_cql import BC, CQL, IQL
from sb3_cql.common import KeywordError, SettingError
from sb3_cql.common.settings import ObservationError
from sb3_cql.data import CollectionSpec, DatasetError, collect_dataset, collection, load_dataset
from sb3_cql.data.__main__ import main as data_cli
from sb3_cql.data.ids import dataset_path, partial_path
from sb3_cql.data.store import DatasetFiles
from sb3_cql.evaluate import main as evaluate_cli
from sb3_cql.protocol.__main__ import main as benchmark_cli

TINY = {"net_arch": [8]}
#: The zoo's CQL run on Panda-v0 in delta actions with tiny networks, in the test's folder.
ZOO_CQL = ["--algo", "cql", "--env", "Panda-v0", "-f", "logs", "--seed", "0", "-n", "4"]
TINY_ZOO = "policy_kwargs:dict(net_arch=[8])"


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> Path:
    """A folder shared by the module's tests: tiny models and one-episode datasets are made once."""
    return tmp_path_factory.mktemp("bad_input")


@pytest.fixture(autouse=True)
def datasets(tmp_path, monkeypatch) -> Path:
    """Each test's own datasets folder (what a refusal leaves there is checked), and its own working folder."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    monkeypatch.chdir(tmp_path)
    return tmp_path / "datasets"


def random_buffer(env: gym.Env, size: int = 32) -> ReplayBuffer:
    buffer = ReplayBuffer(size, env.observation_space, env.action_space)
    rng = np.random.default_rng(0)
    for _ in range(size):
        observation = rng.normal(size=env.observation_space.shape).astype(np.float32)
        action = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)  # scaled, as SB3 stores actions
        buffer.add(observation, observation, action, np.array([0.0]), np.array([False]), [{}])
    return buffer


@pytest.fixture(scope="module")
def model(shared) -> Path:
    """An untrained CQL model of Panda-v0 in delta actions (tiny networks), saved."""
    env = gym.make("Panda-v0", action_mode="delta")
    CQL("MlpPolicy", env, dataset=random_buffer(env), batch_size=8, policy_kwargs=TINY, seed=0).save(shared / "cql_delta")
    env.close()
    return shared / "cql_delta.zip"


def one_line(main, argv: list[str], capsys) -> tuple[int, str]:
    """The exit status and the one line on stderr of a command line's ``main(argv)`` that refuses its input."""
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return exit_.value.code, lines[0]


def zoo_train(argv: list[str], monkeypatch) -> None:
    """``python -m rl_zoo3.train ARGV``, in this process (the plugin is loaded, as in the command)."""
    monkeypatch.setattr(sys, "argv", ["train", *argv])
    train.train()


def zoo_one_line(argv: list[str], monkeypatch, capsys) -> tuple[int, str]:
    return one_line(lambda _: zoo_train(argv, monkeypatch), [], capsys)


def run_folders(root: Path) -> list[Path]:
    return sorted((root / "logs").glob("*/Panda-v0_*"))


def free_port() -> int:
    """A local port nothing listens on."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


# The datasets ----------------------------------------------------------------------------------------------------


def test_a_collection_of_other_settings_is_refused_a_standard_id_and_collects_under_its_own(datasets, capsys):
    code, line = one_line(data_cli, ["collect", "--policy", "noisy", "--noise", "0.2", "--seed", "7", "--episodes", "1"],
                          capsys)  # fmt: skip
    assert code == 2
    assert line == (
        "python -m sb3_cql.data: error: sb3cql/Panda-v0/noisy-v0 is a standard dataset id, defined as 10000 episodes or "
        "its first ones with seed 0, noise 0.03; this collection has seed 7, noise 0.2: give it an id of its own, e.g. "
        "--dataset-id sb3cql/Panda-v0/noisy-custom-v0"
    )
    assert not dataset_path("sb3cql/Panda-v0/noisy-v0").exists() and not partial_path("sb3cql/Panda-v0/noisy-v0").exists()
    with pytest.raises(DatasetError, match="is a standard dataset id"):  # the Python API, an explicit standard id
        collect_dataset(CollectionSpec(policy="pid", seed=3, n_episodes=1), "sb3cql/Panda-v0/pid-v0", progress_bar=False)
    data_cli(["collect", "--policy", "noisy", "--noise", "0.2", "--seed", "7", "--episodes", "1",
              "--dataset-id", "sb3cql/Panda-v0/noisy-custom-v0"])  # fmt: skip
    spec = json.loads(load_dataset("sb3cql/Panda-v0/noisy-custom-v0").storage.metadata["collection"])
    assert (spec["seed"], spec["noise"], spec["n_episodes"]) == (7, 0.2, 1)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seed", "-1"], "seed must be an integer >= 0, got -1"),
        (["--noise", "nan"], "noise must be a finite number >= 0 (std in rad), got nan"),
        (["--episodes", "99999999"], "not enough disk space in"),
    ],
)
def test_a_refused_collection_leaves_nothing_that_blocks_the_corrected_command(args, message, datasets, capsys):
    dataset_id = "sb3cql/Panda-v0/fix-v0"
    code, line = one_line(data_cli, ["collect", "--dataset-id", dataset_id, *args], capsys)
    assert code == 2 and line.startswith("python -m sb3_cql.data: error: ") and message in line
    assert not partial_path(dataset_id).exists() and not dataset_path(dataset_id).exists()
    data_cli(["collect", "--dataset-id", dataset_id, "--episodes", "1"])  # the corrected command, without --overwrite
    assert load_dataset(dataset_id).total_episodes == 1


def test_a_collection_that_kept_no_episode_is_replaced_by_another(datasets):
    files = DatasetFiles("sb3cql/Panda-v0/kept-none-v0")  # a collection stopped before its first episode file
    with files.locked():
        files.start(CollectionSpec(policy="random", n_episodes=5, seed=3).to_json())
    dataset = collect_dataset(CollectionSpec(policy="random", n_episodes=1), files.dataset_id, progress_bar=False)
    assert dataset.total_episodes == 1 and not files.partial.exists()


def test_dataset_ids_that_are_not_ones_are_one_line_and_write_nothing(datasets, tmp_path, capsys):
    for dataset_id in ("sb3cql/Panda-v0/pid", "../../x-v0"):
        code, line = one_line(data_cli, ["collect", "--dataset-id", dataset_id, "--episodes", "1"], capsys)
        assert code == 2 and line == (
            f"python -m sb3_cql.data: error: {dataset_id!r} is not a dataset id: write [NAMESPACE/]NAME-vVERSION, a "
            "version at the end and no '..' (e.g. sb3cql/Panda-v0/pid-v0)"
        )
    assert not any(tmp_path.rglob("*.lock")) and not (tmp_path.parent / ".x-v0.lock").exists()


def test_an_unreachable_cluster_is_one_line_and_leaves_nothing(datasets, tmp_path, capsys):
    address = f"127.0.0.1:{free_port()}"
    code, line = one_line(data_cli, ["collect", "--episodes", "1", "--ray", address], capsys)
    assert code == 2 and line.startswith(f"python -m sb3_cql.data: error: cannot connect to the Ray cluster at {address}: "
                                         f"nothing answers at {address}")  # fmt: skip
    assert not partial_path("sb3cql/Panda-v0/pid-v0").exists() and not dataset_path("sb3cql/Panda-v0/pid-v0").exists()
    results = tmp_path / "results"
    code, line = one_line(benchmark_cli, ["--algos", "pid", "--seeds", "1", "--ray", address, "--results-dir", str(results)],
                          capsys)  # fmt: skip
    assert code == 2 and f"cannot connect to the Ray cluster at {address}" in line and not results.exists()


def test_an_empty_dataset_and_a_mix_across_action_modes_are_named_as_such(datasets, capsys):
    env = gym.make("Panda-v0")
    (dataset_path("sb3cql/Panda-v0/empty-v0") / "data").mkdir(parents=True)
    storage = MinariStorage.new(dataset_path("sb3cql/Panda-v0/empty-v0") / "data", env.observation_space, env.action_space,
                                env.spec, data_format="hdf5")  # fmt: skip
    storage.update_metadata({"dataset_id": "sb3cql/Panda-v0/empty-v0", "minari_version": minari.__version__})
    code, line = one_line(data_cli, ["info", "sb3cql/Panda-v0/empty-v0"], capsys)
    assert code == 2 and "sb3cql/Panda-v0/empty-v0 at" in line and "holds no episodes" in line
    collect_dataset(CollectionSpec(n_episodes=1), "sb3cql/Panda-v0/a-v0", progress_bar=False)
    delta = CollectionSpec(n_episodes=1, env_kwargs={"action_mode": "delta"})
    collect_dataset(delta, "sb3cql/Panda-v0/d-v0", progress_bar=False)
    capsys.readouterr()
    code, line = one_line(data_cli, ["mix", "--dataset-id", "sb3cql/Panda-v0/m-v0", "sb3cql/Panda-v0/a-v0",
                                     "sb3cql/Panda-v0/d-v0"], capsys)  # fmt: skip
    assert code == 2 and line == (
        "python -m sb3_cql.data: error: cannot mix datasets of different envs or action modes (sb3cql/Panda-v0/a-v0: "
        "Panda-v0, action_mode 'absolute'; sb3cql/Panda-v0/d-v0: Panda-v0, action_mode 'delta'): mix datasets of one env "
        "and action mode"
    )
    assert not dataset_path("sb3cql/Panda-v0/m-v0").exists()


# The tasks' physics ----------------------------------------------------------------------------------------------


def test_non_finite_or_mistyped_physics_are_refused_where_the_task_is_made(capsys, monkeypatch):
    for kwargs in ({"object_mass": float("nan")}, {"gravity": float("inf")}, {"gravity": "x"}, {"object_radius": 0.0}):
        with pytest.raises(ConfigError, match=f"^{next(iter(kwargs))} must be"):
            gym.make("Panda-v0", **kwargs)
    code, line = one_line(evaluate_cli, ["pid", "--env", "Panda-v0", "-n", "1", "--env-kwargs", "gravity:'x'"], capsys)
    assert code == 2 and line == "python -m sb3_cql.evaluate: error: pid on Panda-v0: gravity must be a finite number, got 'x'"
    code, line = zoo_one_line([*ZOO_CQL, "--env-kwargs", "object_mass:float('nan')"], monkeypatch, capsys)
    assert code == 2 and line == "python -m rl_zoo3.train: error: object_mass must be a finite number, got nan"
    assert run_folders(Path.cwd()) == []


# The zoo ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("algo", "items", "message"),
    [
        ("cql", ["batch_sise:64"], "CQL got unexpected keyword arguments: batch_sise (did you mean batch_size?)"),
        ("bc", ["gamma:0.9"], "BC does not take gamma: BC trains its actor on the data's actions"),
        (
            "cql",
            ["learning_rate:'abc'"],
            "--hyperparams learning_rate:'abc': learning_rate must be a number >= 0 or a "
            "linear schedule 'lin_<initial value>'; e.g. learning_rate:0.0003 or",
        ),
        ("cql", ["learning_rate:-0.001"], "learning_rate must be a number >= 0, got -0.001"),
        (
            "iql",
            ["actor_learning_rate:'lin_x'"],
            "--hyperparams actor_learning_rate:'lin_x': actor_learning_rate must be a number >= 0 or a "
            "linear schedule 'lin_<initial value>'; e.g. actor_learning_rate:0.0003 or",
        ),
        (
            "cql",
            ["dataset:sb3cql/Panda-v0/pid-v0"],
            "--hyperparams dataset:sb3cql/Panda-v0/pid-v0: NameError: name "
            "'sb3cql' is not defined; write KEY:VALUE with a Python value: a number "
            "as it is (batch_size:64), a string in quotes inside the shell's "
            "(dataset:\"'sb3cql/Panda-v0/pid-v0'\")",
        ),
        ("cql", ["batch_size:abc"], "--hyperparams batch_size:abc: NameError: name 'abc' is not defined;"),
        ("cql", ["reward_scale:float('nan')"], "reward_scale must be a finite number, got nan"),
        ("cql", ["actor_learning_rate:-1.0"], "actor_learning_rate must be a number >= 0, got -1.0"),
    ],
)
def test_zoo_hyperparameters_it_cannot_use_are_one_line_and_leave_no_run_folder(algo, items, message, monkeypatch, capsys):
    argv = [*ZOO_CQL, "--hyperparams", TINY_ZOO, *items]
    argv[1] = algo
    code, line = zoo_one_line(argv, monkeypatch, capsys)
    assert code == 2 and line.startswith("python -m rl_zoo3.train: error: ") and message in line, line
    assert run_folders(Path.cwd()) == []


@pytest.fixture(scope="module")
def delta_dataset(shared) -> str:
    """A one-episode PD dataset in delta actions, for the zoo runs that train."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(shared / "datasets"))
        collect_dataset(CollectionSpec(n_episodes=1, env_kwargs={"action_mode": "delta"}), "sb3cql/Panda-v0/tiny-delta-v0",
                        progress_bar=False)  # fmt: skip
    return str(shared / "datasets")


def test_a_zoo_run_that_diverges_ends_on_one_line_without_a_model_less_folder(delta_dataset, monkeypatch, capsys):
    monkeypatch.setenv("MINARI_DATASETS_PATH", delta_dataset)
    argv = [*ZOO_CQL, "--hyperparams", TINY_ZOO, "dataset:'sb3cql/Panda-v0/tiny-delta-v0'", "batch_size:8",
            "reward_scale:1e300"]  # fmt: skip
    code, line = zoo_one_line(argv, monkeypatch, capsys)
    assert code == 2
    assert re.match(
        r"python -m rl_zoo3.train: error: CQL's critic loss is (nan|inf) at gradient step 1: training diverged", line
    )
    assert run_folders(Path.cwd()) == []


def test_ctrl_c_while_the_data_of_an_i_run_are_collected_keeps_no_model(model, monkeypatch, capsys, datasets):
    """``-i MODEL`` whose dataset, a standard one, is collected as training starts: Ctrl-C there keeps no model and
    no run folder (the collection says what it kept)."""
    dataset_id = "sb3cql/Panda-v0/pid-delta-1k-v0"
    spec_file = DatasetFiles(dataset_id).spec_file
    main_thread = threading.get_ident()

    def interrupt_once_collecting() -> None:
        while not spec_file.exists():
            threading.Event().wait(0.05)
        signal.pthread_kill(main_thread, signal.SIGINT)

    threading.Thread(target=interrupt_once_collecting, daemon=True).start()
    argv = [*ZOO_CQL, "-i", str(model), "--hyperparams", TINY_ZOO, f"dataset:'{dataset_id}'", "batch_size:8"]
    with pytest.raises(SystemExit) as exit_:
        zoo_train(argv, monkeypatch)
    err = capsys.readouterr().err
    assert exit_.value.code == 130 and "Traceback" not in err and "the model at that step" not in err
    removed = [line for line in err.splitlines() if line.startswith("interrupted before training started: no model saved")]
    assert removed == [f"interrupted before training started: no model saved, {Path('logs/cql/Panda-v0_1')} removed"]
    assert run_folders(Path.cwd()) == []


# Evaluation ------------------------------------------------------------------------------------------------------


def test_evaluate_refuses_an_output_that_is_the_model_or_a_folder_before_any_episode(model, tmp_path, capsys):
    copy = tmp_path / "model.zip"
    copy.write_bytes(model.read_bytes())
    (tmp_path / "link.zip").symlink_to(copy)
    for output in (copy, tmp_path / "link.zip"):  # the same file by another path
        code, line = one_line(evaluate_cli, [str(copy), "--algo", "cql", "--env", "Panda-v0", "--seeds", "0",
                                             "--output", str(output)], capsys)  # fmt: skip
        assert code == 2 and line.startswith(f"python -m sb3_cql.evaluate: error: --output {output} is the model")
    assert copy.read_bytes() == model.read_bytes()
    code, line = one_line(evaluate_cli, [str(copy), "--algo", "cql", "--seeds", "0", "--output", str(tmp_path)], capsys)
    assert code == 2 and line.startswith(f"python -m sb3_cql.evaluate: error: --output {tmp_path} is a folder")
    code, line = one_line(evaluate_cli, [str(copy), "--algo", "cql", "--seeds", "0", "--output",
                                         str(copy / "out.json")], capsys)  # fmt: skip
    assert code == 2 and "cannot be written" in line


def test_evaluate_prints_the_results_it_cannot_write(tmp_path, capsys):
    output = tmp_path / f"{'x' * 245}.json"  # a name the file system takes, its temporary file's (longer) it refuses
    with pytest.raises(SystemExit) as exit_:
        evaluate_cli(["pid", "--env", "Panda-v0", "--seeds", "0", "--output", str(output)])
    out, err = capsys.readouterr()
    assert exit_.value.code == 2 and "Traceback" not in err
    assert out.splitlines() == ["Panda-v0: success rate 1.000 over 1 episodes (seeds 0, absolute actions)"]
    assert err.splitlines() == [f"python -m sb3_cql.evaluate: error: cannot write --output {output} (File name too long): "
                                "the results are the lines printed"]  # fmt: skip
    assert list(tmp_path.iterdir()) == []


def test_evaluate_input_errors_are_one_line(model, tmp_path, capsys):
    code, line = one_line(evaluate_cli, ["pid", "--env", "Panda-v0", "--seed", "-1"], capsys)
    assert code == 2 and line == "python -m sb3_cql.evaluate: error: --seed must be >= 0 (numpy seeds), got -1"
    code, line = one_line(evaluate_cli, [str(model), "--algo", "cql", "--env", "Panda-v0", "--env-kwargs", "colour:1"],
                          capsys)  # fmt: skip
    assert code == 2 and line.startswith("python -m sb3_cql.evaluate: error: --env-kwargs: unknown keyword(s) colour: the "
                                         "tasks take render_mode, action_mode")  # fmt: skip
    assert "'absolute'" not in line
    stripped = tmp_path / "no_policy.zip"
    with zipfile.ZipFile(model) as source, zipfile.ZipFile(stripped, "w") as target:
        for name in source.namelist():
            if name != "policy.pth":
                target.writestr(name, source.read(name))
    code, line = one_line(evaluate_cli, [str(stripped), "--algo", "cql", "--env", "Panda-v0"], capsys)
    assert code == 2 and line == (
        f"python -m sb3_cql.evaluate: error: cannot load {stripped} as a cql model: it holds no policy parameters (no "
        "policy.pth member)"
    )


# The protocol ----------------------------------------------------------------------------------------------------


def test_the_protocol_refuses_bad_counts_and_folders_before_writing_and_runs_the_corrected_command(tmp_path, capsys):
    results = tmp_path / "results"
    protocol = ["--algos", "pid", "--seeds", "1", "--tasks", "Panda-v0", "--results-dir", str(results), "--no-filmstrips"]
    for args, message in (
        (["--episodes", "0"], "--episodes must be an integer >= 1, got 0"),
        (["--workers", "0"], "--workers must be an integer >= 1, got 0"),
        (["--zoo-args", "--hyperparams 'batch_size:64"], '--zoo-args "--hyperparams \'batch_size:64": No closing quotation'),
    ):
        code, line = one_line(benchmark_cli, [*protocol, *args], capsys)
        assert code == 2 and line.startswith(f"python -m sb3_cql.protocol: error: {message}"), line
        assert not results.exists()
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for folder, message in ((a_file, f"--results-dir {a_file} is a file"), (a_file / "r", "cannot be written")):
        code, line = one_line(benchmark_cli, [*protocol, "--results-dir", str(folder)], capsys)
        assert code == 2 and message in line
    benchmark_cli([*protocol, "--episodes", "1"])
    record_path = results / "records" / "eval" / "pid-seed1-Panda-v0.json"
    record = json.loads(record_path.read_text())
    assert record["episodes"] == 1 and np.isfinite(record["success_rate"])
    umask = os.umask(0o022)
    os.umask(umask)
    for path in (record_path, results / "protocol.json", results / "results.json", results / "table.md"):
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask, path


# The Python API --------------------------------------------------------------------------------------------------


def test_ctrl_c_during_a_gradient_step_acts_after_it(model):
    """A SIGINT that arrives between the critics' and the actor's updates: the model stops after the whole step, every
    optimiser having stepped as many times as the model counts updates."""
    env = gym.make("Pendulum-v1")
    cql = CQL("MlpPolicy", env, dataset=random_buffer(env, 64), batch_size=8, bc_steps=0, policy_kwargs=TINY, seed=0)
    sent = []

    def interrupt_once(*_):
        if not sent:
            sent.append(True)
            os.kill(os.getpid(), signal.SIGINT)

    cql.critic.optimizer.register_step_post_hook(interrupt_once)
    with pytest.raises(KeyboardInterrupt):
        cql.learn(5)

    def steps(optimizer) -> int:
        return int(next(iter(optimizer.state.values()))["step"])

    assert cql.num_timesteps == cql._n_updates == 1
    assert steps(cql.critic.optimizer) == steps(cql.actor.optimizer) == steps(cql.ent_coef_optimizer) == 1


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"ent_coef": -1.0}, "ent_coef must be a number >= 0, got -1.0"),
        ({"target_entropy": float("nan")}, "target_entropy must be a finite number, got nan"),
        ({"policy_kwargs": {"net_arch": [0]}}, "net_arch must be a list of layer sizes (integers >= 1) or a dict of them"),
        ({"learning_rate": float("inf")}, "learning_rate must be a finite number, got inf"),
    ],
)
def test_settings_torch_would_fail_on_are_refused_naming_them(options, message):
    env = gym.make("Pendulum-v1")
    with pytest.raises(SettingError, match=f"^{re.escape(message)}"):
        CQL("MlpPolicy", env, dataset=random_buffer(env), **{"policy_kwargs": TINY, **options})


def test_a_frozen_target_and_images_held_as_the_policy_sees_them_are_accepted(tmp_path):
    env = gym.make("Pendulum-v1")
    cql = CQL("MlpPolicy", env, dataset=random_buffer(env), tau=0, batch_size=8, bc_steps=0, policy_kwargs=TINY)
    target = [parameter.clone() for parameter in cql.critic_target.parameters()]
    cql.learn(2)
    assert all(bool((a == b).all()) for a, b in zip(target, cql.critic_target.parameters(), strict=True))
    image_env = FakeImageEnv(screen_height=40, screen_width=40, n_channels=2, discrete=False)  # channel-last
    first = gym.spaces.Box(0, 255, (2, 40, 40), np.uint8)  # channel-first: what VecTransposeImage hands the policy
    storage = MinariStorage.new(tmp_path / "images", first, image_env.action_space, data_format="hdf5")
    rng = np.random.default_rng(0)
    observations = rng.integers(0, 255, (6, 2, 40, 40), dtype=np.uint8)
    storage.update_episodes([EpisodeBuffer(
        id=0, seed=0, observations=observations,
        actions=rng.uniform(-1, 1, (5, *image_env.action_space.shape)).astype(np.float32), rewards=np.zeros(5),
        terminations=np.zeros(5, bool), truncations=np.zeros(5, bool))])  # fmt: skip
    storage.update_metadata({"dataset_id": "images-v0", "minari_version": minari.__version__})
    for algo in (CQL, BC):
        model = algo("CnnPolicy", image_env, dataset=MinariDataset(tmp_path / "images"), batch_size=4, buffer_size=8,
                     policy_kwargs={"net_arch": [8]})  # fmt: skip
        assert model.replay_buffer.size() == 5
        np.testing.assert_array_equal(model.replay_buffer.observations[:5, 0], observations[:-1])


# What an id, a list or a keyword says is what is done -------------------------------------------------------------


@contextlib.contextmanager
def small_disk(path: Path, pages: int, read_only: bool = False) -> Iterator[Path]:
    """A tmpfs of ``pages`` pages of 4 kB at ``path`` (root only: the test is skipped elsewhere)."""
    path.mkdir(parents=True)
    options = f"size={pages * 4096}" + (",ro" if read_only else "")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {mounted.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


@pytest.fixture(scope="module")
def pendulum_models(shared) -> dict[str, Path]:
    """Untrained IQL and BC models of Pendulum-v1 (tiny networks), saved."""
    env = gym.make("Pendulum-v1")
    for name, algo in (("iql", IQL), ("bc", BC)):
        algo("MlpPolicy", env, dataset=random_buffer(env), batch_size=8, policy_kwargs=TINY, seed=0).save(shared / name)
    return {"iql": shared / "iql.zip", "bc": shared / "bc.zip"}


def test_a_standard_id_holds_its_own_task_s_data_and_names_a_partial_collection(datasets, monkeypatch, capsys):
    standard = "sb3cql/Panda-v0/pid-v0"
    code, line = one_line(data_cli, ["collect", "--env", "PandaForce-v0", "--episodes", "1", "--dataset-id", standard], capsys)
    assert code == 2 and line == (
        "python -m sb3_cql.data: error: sb3cql/Panda-v0/pid-v0 is a standard dataset id, defined as 10000 episodes or its "
        "first ones with env_id 'Panda-v0'; this collection has env_id 'PandaForce-v0': give it an id of its own, e.g. "
        "--dataset-id sb3cql/PandaForce-v0/pid-v0"
    )
    code, line = one_line(data_cli, ["collect", "--action-mode", "delta", "--episodes", "1", "--dataset-id", standard], capsys)
    assert code == 2 and "this collection has env_kwargs {'action_mode': 'delta'}: give it an id of its own, e.g. " \
                        "--dataset-id sb3cql/Panda-v0/pid-delta-v0" in line  # fmt: skip
    assert not dataset_path(standard).exists() and not partial_path(standard).exists()
    with monkeypatch.context() as patch:  # another task's data under the id, as a collection before this check wrote them
        patch.setattr(collection, "_check_standard", lambda spec, dataset_id: None)
        collect_dataset(CollectionSpec(env_id="PandaForce-v0", n_episodes=1), standard, progress_bar=False)
    with pytest.raises(DatasetError) as refused:
        IQL("MlpPolicy", gym.make("Panda-v0"), dataset=standard, policy_kwargs=TINY)
    assert str(refused.value) == (
        f"sb3cql/Panda-v0/pid-v0 is a standard dataset id, defined as 10000 episodes or its first ones with env_id "
        f"'Panda-v0'; the dataset at {dataset_path(standard)} has env_id 'PandaForce-v0': move it to an id of its own "
        "(python -m sb3_cql.data info sb3cql/Panda-v0/pid-v0 shows what it holds), then python -m sb3_cql.data collect "
        "--env Panda-v0 --policy pid --episodes 10000 --seed 0 --dataset-id sb3cql/Panda-v0/pid-v0 collects "
        "sb3cql/Panda-v0/pid-v0"
    )
    data_cli(["collect", "--policy", "pid-regrasp", "--episodes", "1"])  # the first episode of a standard id's 10,000
    capsys.readouterr()
    model = IQL("MlpPolicy", "Panda-v0", dataset="sb3cql/Panda-v0/pid-regrasp-v0", batch_size=8, policy_kwargs=TINY)
    assert capsys.readouterr().err.splitlines() == [
        "sb3cql/Panda-v0/pid-regrasp-v0 holds 1 of the 10000 episodes its id defines (their first ones): using these; "
        "python -m sb3_cql.data collect --env Panda-v0 --policy pid-regrasp --episodes 10000 --seed 0 --dataset-id "
        "sb3cql/Panda-v0/pid-regrasp-v0 --overwrite collects them all"
    ]
    assert model.replay_buffer.size() == load_dataset("sb3cql/Panda-v0/pid-regrasp-v0").total_steps


def test_lists_that_repeat_a_value_are_refused_naming_the_option_and_the_value(datasets, tmp_path, capsys):
    results = tmp_path / "results"
    for args, message in (
        (["--algos", "cql", "--seeds", "5", "5", "--workers", "2"], "--seeds 5 5: 5 is given more than once; give each once"),
        (["--algos", "pid", "pid", "--tasks", "Panda-v0", "Panda-v0"], "--algos pid pid: pid is given more than once"),
        (["--algos", "pid", "--tasks", "Panda-v0", "PandaForce-v0", "Panda-v0"], "--tasks Panda-v0 PandaForce-v0 Panda-v0: "
                                                                                 "Panda-v0 is given more than once"),
    ):  # fmt: skip
        code, line = one_line(benchmark_cli, [*args, "--results-dir", str(results)], capsys)
        assert code == 2 and line.startswith(f"python -m sb3_cql.protocol: error: {message}"), line
        assert not results.exists()
    code, line = one_line(evaluate_cli, ["pid", "--env", "Panda-v0", "--seeds", "1-5", "3"], capsys)
    assert code == 2 and line == ("python -m sb3_cql.evaluate: error: --seeds: 3 is given more than once (ranges included): "
                                  "give each once")  # fmt: skip
    code, line = one_line(evaluate_cli, ["pid", "--env", "Panda-v0", "Panda-v0", "-n", "1"], capsys)
    assert code == 2 and line.startswith("python -m sb3_cql.evaluate: error: --env: Panda-v0 is given more than once")
    code, line = one_line(data_cli, ["mix", "--dataset-id", "sb3cql/Panda-v0/m-v0", "a-v0", "b-v0", "a-v0"], capsys)
    assert code == 2 and line == ("python -m sb3_cql.data: error: a-v0 given more than once: give each dataset to mix "
                                  "once")  # fmt: skip
    code, line = one_line(data_cli, ["mix", "--dataset-id", "sb3cql/Panda-v0/noisy-v0", "a-v0", "b-v0"], capsys)
    assert code == 2 and "sb3cql/Panda-v0/noisy-v0 is a standard dataset id" in line
    assert not datasets.exists() or not any(datasets.rglob("*-v0"))


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # the test's stderr is the command's
        pass


def test_a_web_server_at_the_ray_address_is_one_line_within_seconds_and_leaves_nothing(datasets, tmp_path, capsys):
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), QuietHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    address = f"127.0.0.1:{server.server_address[1]}"
    try:
        start = time.monotonic()
        code, line = one_line(data_cli, ["collect", "--episodes", "1", "--ray", address], capsys)
        assert time.monotonic() - start < 10
        assert code == 2 and line == (
            f"python -m sb3_cql.data: error: cannot connect to the Ray cluster at {address}: a web server answers at "
            f"{address}, not Ray (the address of its GCS, 6379 by default, or ray:// and its client server's, 10001; not "
            "its dashboard's); start it (ray start --head) or give the address that ray status prints"
        )
        assert not datasets.exists() or not any(datasets.rglob("*"))  # no lock file, no partial collection
        results = tmp_path / "results"
        code, line = one_line(benchmark_cli, ["--algos", "pid", "--seeds", "1", "--ray", address, "--results-dir",
                                              str(results)], capsys)  # fmt: skip
        assert code == 2 and f"a web server answers at {address}, not Ray" in line and not results.exists()
    finally:
        server.shutdown()
        server.server_close()


def test_keywords_load_does_not_take_are_refused_naming_the_closest(model, pendulum_models):
    env = gym.make("Panda-v0", action_mode="delta")
    for load, message in (
        (lambda: CQL.load(model, env=env, online_fracton=0.5), "CQL got unexpected keyword arguments: online_fracton (did "
                                                               "you mean online_fraction?)"),
        (lambda: IQL.load(pendulum_models["iql"], expectle=0.95), "IQL got unexpected keyword arguments: expectle (did you "
                                                                  "mean expectile?)"),
        (lambda: CQL.load(model, expectile=0.9), "CQL got unexpected keyword arguments: expectile"),
        (lambda: BC.load(pendulum_models["bc"], best_of_n=4), "BC got unexpected keyword arguments: best_of_n"),
    ):  # fmt: skip
        with pytest.raises(KeywordError) as refused:
            load()
        assert str(refused.value) == message and "\n" not in str(refused.value)


def test_settings_that_would_fail_later_are_refused_or_trained_with(pendulum_models, tmp_path):
    env = gym.make("Pendulum-v1")
    message = re.escape("best_of_n must be an integer in [1, 4096] (the candidate actions drawn and valued at each "
                        "decision; more would not fit in memory), got 1000000000")  # fmt: skip
    with pytest.raises(SettingError, match=f"^{message}$"):
        IQL("MlpPolicy", env, dataset=random_buffer(env), policy_kwargs=TINY, best_of_n=10**9)
    with pytest.raises(SettingError, match=f"^{message}$"):
        IQL.load(pendulum_models["iql"], best_of_n=10**9)
    for options in ({"n_steps": 3}, {"action_chunk": 2}):  # gamma 1: the n-step sums need no 1 / (1 - gamma)
        cql = CQL("MlpPolicy", env, dataset=random_buffer(env, 64), gamma=1.0, batch_size=8, policy_kwargs=TINY, **options)
        cql.learn(2)
        assert cql._n_updates == 2
    with pytest.raises(SettingError, match="^reward_bias with n_steps > 1 needs gamma < 1"):
        CQL("MlpPolicy", env, dataset=random_buffer(env), gamma=1.0, n_steps=3, reward_bias=-1.0, policy_kwargs=TINY)


def test_datasets_that_are_no_data_are_one_line(datasets):
    env = gym.make("Pendulum-v1")
    with pytest.raises(DatasetError, match=r"^dataset: the replay buffer holds no transitions$"):
        CQL("MlpPolicy", env, dataset=ReplayBuffer(8, env.observation_space, env.action_space), policy_kwargs=TINY)
    for dataset, name in ((np.zeros((10, 3)), "ndarray"), (42, "int")):
        with pytest.raises(DatasetError) as refused:
            CQL("MlpPolicy", env, dataset=dataset, policy_kwargs=TINY)
        assert str(refused.value) == f"dataset must be a Minari dataset, its id or a filled SB3 ReplayBuffer, got {name}"
    assert not datasets.exists()


def without_member(model: Path, member: str, target: Path) -> Path:
    """A copy of the model file ``model`` without its ``member``."""
    with zipfile.ZipFile(model) as source, zipfile.ZipFile(target, "w") as copy:
        for name in source.namelist():
            if name != member:
                copy.writestr(name, source.read(name))
    return target


def test_model_files_that_cannot_be_loaded_or_written_are_one_line(model, pendulum_models, tmp_path, capsys):
    stripped = without_member(model, "policy.pth", tmp_path / "no_policy.zip")
    with pytest.raises(ValueError) as refused:
        CQL.load(stripped)
    assert str(refused.value) == f"cannot load {stripped}: it holds no policy parameters (no policy.pth member)"
    iql = str(pendulum_models["iql"])
    code, line = one_line(evaluate_cli, [iql, "--algo", "cql", "--env", "Panda-v0", "-n", "1"], capsys)
    assert code == 2 and line == (f"python -m sb3_cql.evaluate: error: cannot load {iql} as a cql model: it holds an IQL "
                                  "model; give --algo iql")  # fmt: skip
    cql = CQL.load(model)
    with small_disk(tmp_path / "read_only", 4, read_only=True) as folder, pytest.raises(OSError) as refused:
        cql.save(folder / "model")
    assert str(refused.value) == f"[Errno 30] Read-only file system: '{folder / 'model.zip'}'"
    assert refused.value.__cause__ is None and refused.value.__suppress_context__


class NaNAfterReset(gym.Wrapper):
    """Observations with a NaN at index 1 after the first one."""

    def step(self, action):
        observation, *rest = self.env.step(action)
        observation = observation.copy()
        observation[1] = np.nan
        return observation, *rest


def test_a_non_finite_observation_is_named_at_the_step_it_arrives():
    env = gym.make("Pendulum-v1")
    cql = CQL("MlpPolicy", env, dataset=random_buffer(env), batch_size=8, policy_kwargs=TINY)
    with pytest.raises(ObservationError) as refused:
        cql.predict(np.array([1.0, np.nan, 0.0], dtype=np.float32))
    assert str(refused.value) == ("the observation holds nan at index [1] (shape [3]): every observation must be finite; "
                                  "check the env and its wrappers")  # fmt: skip
    finetuning = CQL("MlpPolicy", NaNAfterReset(env), dataset=random_buffer(env), batch_size=8, policy_kwargs=TINY,
                     online_fraction=0.5)  # fmt: skip
    with pytest.raises(ObservationError, match=re.escape("the env's observation holds nan at index [0, 1] (shape [1, 3])")):
        finetuning.learn(4)
    assert finetuning._n_updates == 0


# The zoo's files and models --------------------------------------------------------------------------------------


def test_a_zoo_run_on_a_full_disk_or_a_read_only_folder_is_one_line(delta_dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MINARI_DATASETS_PATH", delta_dataset)
    argv = [*ZOO_CQL, "--eval-freq", "2", "--eval-episodes", "1", "--hyperparams", TINY_ZOO,
            "dataset:'sb3cql/Panda-v0/tiny-delta-v0'", "batch_size:8"]  # fmt: skip
    with small_disk(tmp_path / "full", 16) as disk:
        (disk / "filler").write_bytes(bytes(12 * 4096))  # a page for each of the run's 4 small files, none for more
        monkeypatch.chdir(disk)
        code, line = zoo_one_line(argv, monkeypatch, capsys)
        assert code == 2 and line == (
            f"python -m rl_zoo3.train: error: cannot write {Path('logs/cql/Panda-v0_1')} (No space left on device): free "
            "some disk space, or write to another disk, and run the command again"
        )
        assert run_folders(disk) == [] and not list(disk.rglob("evaluations.npz"))
    with small_disk(tmp_path / "read_only", 4, read_only=True) as folder:
        monkeypatch.chdir(folder)
        code, line = zoo_one_line(argv, monkeypatch, capsys)
        assert code == 2 and line == ("python -m rl_zoo3.train: error: cannot write logs (Read-only file system): give -f a "
                                      "folder this user may write in")  # fmt: skip


def test_a_zoo_run_from_another_algorithm_s_model_is_one_line_without_a_run_folder(pendulum_models, monkeypatch, capsys):
    iql = pendulum_models["iql"]
    code, line = zoo_one_line([*ZOO_CQL, "-i", str(iql), "--hyperparams", TINY_ZOO], monkeypatch, capsys)
    assert code == 2 and line == (f"python -m rl_zoo3.train: error: {iql} holds an IQL model: load it with IQL.load (in "
                                  "the zoo, --algo iql)")  # fmt: skip
    assert run_folders(Path.cwd()) == []
