"""Collection of Minari datasets and their loading into SB3's ReplayBuffer."""

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time

import gymnasium as gym
import minari
import numpy as np
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer

import envs
from sb3_cql.data import (
    DEFAULT_NOISE,
    CollectionSpec,
    DatasetError,
    arrays_digest,
    collect_dataset,
    dataset_path,
    ensure_dataset,
    fill_replay_buffer,
    load_dataset,
    mix_datasets,
)
from sb3_cql.data import collection as collection_module
from sb3_cql.data.__main__ import main as data_cli
from sb3_cql.data.store import DatasetFiles


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    return tmp_path / "datasets"


def episodes_of(dataset):
    return list(dataset.iterate_episodes())


def assert_same_data(first, second):
    assert first.total_episodes == second.total_episodes
    for a, b in zip(episodes_of(first), episodes_of(second), strict=True):
        for field in ("observations", "actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_pid_collection_is_a_minari_dataset():
    dataset = collect_dataset(CollectionSpec(n_episodes=3), progress_bar=False)
    assert dataset.spec.dataset_id == "sb3cql/Panda-v0/pid-v0"
    loaded = minari.load_dataset("sb3cql/Panda-v0/pid-v0")
    assert loaded.total_episodes == 3
    metadata = loaded.storage.metadata
    assert metadata["success_rate"] == 1.0 and metadata["env_id"] == "Panda-v0"
    assert "kp" in metadata["controller"]
    for episode in loaded.iterate_episodes():
        steps = len(episode.rewards)
        assert episode.observations.shape == (steps + 1, 29) and episode.actions.shape == (steps, 9)
        assert episode.rewards[-1] == 1.0 and episode.terminations[-1] and not episode.truncations.any()
    env = loaded.recover_environment()
    assert env.spec.id == "Panda-v0" and env.unwrapped.action_mode == "absolute"
    assert env.observation_space == loaded.observation_space


def test_collection_does_not_depend_on_the_number_of_workers():
    spec = CollectionSpec(policy="noisy", n_episodes=3, seed=5)
    one = collect_dataset(spec, "sb3cql/Panda-v0/one-v0", workers=1, progress_bar=False)
    two = collect_dataset(spec, "sb3cql/Panda-v0/two-v0", workers=2, progress_bar=False)
    assert_same_data(one, two)
    # the digest of the arrays in each one's metadata says so, and is the digest of the arrays read back
    assert one.storage.metadata["arrays_sha256"] == two.storage.metadata["arrays_sha256"] == arrays_digest(two)
    other = collect_dataset(dataclasses.replace(spec, seed=6), "sb3cql/Panda-v0/other-v0", progress_bar=False)
    assert arrays_digest(other) == other.storage.metadata["arrays_sha256"] != arrays_digest(one)
    packages = json.loads(one.storage.metadata["packages"])
    assert packages["numpy"] == np.__version__ and packages["gymnasium"] == gym.__version__
    assert packages["minari"] == minari.__version__ and packages["pybullet"]


def test_noisy_policy_records_executed_and_clean_actions():
    dataset = collect_dataset(CollectionSpec(policy="noisy", n_episodes=2, noise=0.03), progress_bar=False)
    for episode in dataset.iterate_episodes():
        clean = episode.infos["clean_action"]
        assert clean.shape == (len(episode.rewards) + 1, 9)
        noise = episode.actions - clean[:-1]
        assert 0.02 < noise[:, :7].std() < 0.04  # Gaussian noise on the arm targets ...
        np.testing.assert_array_equal(noise[:, 7:], 0.0)  # ... and none on the fingers


def test_delta_mode_dataset_has_its_own_id_and_unit_actions():
    spec = CollectionSpec(n_episodes=1, env_kwargs={"action_mode": "delta"})
    dataset = collect_dataset(spec, progress_bar=False)
    assert dataset.spec.dataset_id == "sb3cql/Panda-v0/pid-delta-v0"
    assert np.abs(dataset[0].actions).max() <= 1.0
    assert dataset.recover_environment().unwrapped.action_mode == "delta"


def test_regrasping_policies_collect_with_the_regrasping_pd_controller():
    spec = CollectionSpec(policy="noisy-regrasp", n_episodes=1)
    assert spec.noise == DEFAULT_NOISE and spec.controller == "pid-regrasp"
    assert CollectionSpec(policy="noisy").controller == "pid" and CollectionSpec(policy="random").controller is None
    dataset = ensure_dataset("sb3cql/Panda-v0/noisy-regrasp-delta-v0", n_episodes=1, progress_bar=False)
    assert json.loads(dataset.storage.metadata["controller"])["dropped_distance"] == envs.pd_controller.DROPPED_DISTANCE
    plain = collect_dataset(CollectionSpec(n_episodes=1), progress_bar=False)
    assert "dropped_distance" not in json.loads(plain.storage.metadata["controller"])


def test_random_yaw_collection_records_its_yaws_and_is_reproducible():
    spec = CollectionSpec(policy="noisy-regrasp-yaw", n_episodes=2, seed=5)
    assert spec.controller == "pid-regrasp-yaw" and spec.noise == DEFAULT_NOISE
    one = collect_dataset(spec, "sb3cql/Panda-v0/yaw-one-v0", workers=1, progress_bar=False)
    two = collect_dataset(spec, "sb3cql/Panda-v0/yaw-two-v0", workers=2, progress_bar=False)
    assert_same_data(one, two)  # the yaws of episode i come from (seed, i), whichever worker runs it
    parameters = json.loads(one.storage.metadata["controller"])
    assert parameters["yaw"].startswith("random") and parameters["yaw_range"] == [-np.pi / 2, np.pi / 2]
    assert "SeedSequence(seed)" in parameters["yaw_seed"] and parameters["yaw_episode_seed"] == (
        "episode i: PDController.seed((5, i))"
    )
    fixed = collect_dataset(dataclasses.replace(spec, policy="noisy-regrasp"), "sb3cql/Panda-v0/yaw-fixed-v0",
                            progress_bar=False)  # fmt: skip
    assert "yaw" not in json.loads(fixed.storage.metadata["controller"])
    # The same episodes (same resets, same noise generator) with another hand yaw: other actions.
    np.testing.assert_array_equal(one[0].observations[0], fixed[0].observations[0])
    assert not np.array_equal(one[0].actions[:20], fixed[0].actions[:20])
    with pytest.raises(ValueError, match="pid-regrasp-aligned is a reference controller"):
        CollectionSpec(policy="pid-regrasp-aligned")


def test_existing_dataset_is_not_overwritten_without_asking():
    spec = CollectionSpec(policy="random", n_episodes=1)
    collect_dataset(spec, progress_bar=False)
    with pytest.raises(FileExistsError, match="overwrite"):
        collect_dataset(spec, progress_bar=False)
    replaced = collect_dataset(CollectionSpec(policy="random", n_episodes=2), overwrite=True, progress_bar=False)
    assert replaced.total_episodes == 2


def interrupt_collection_at(monkeypatch, interrupted_index: int, calls: list[int], write_every: int | None = 1):
    """Make episode ``interrupted_index`` raise KeyboardInterrupt (as Ctrl-C does), write every ``write_every``
    episodes (``None``: ``WRITE_EVERY``), record the episodes run in ``calls``; return the real episode function."""
    run_episode = collection_module._run_episode

    def interrupted(index):
        calls.append(index)
        if index == interrupted_index:
            raise KeyboardInterrupt
        return run_episode(index)

    if write_every is not None:
        monkeypatch.setattr(collection_module, "WRITE_EVERY", write_every)
    monkeypatch.setattr(collection_module, "_run_episode", interrupted)
    return run_episode


def test_interrupted_collection_keeps_its_episodes_says_so_and_resumes(monkeypatch, capsys):
    spec = CollectionSpec(policy="noisy", n_episodes=4)
    calls = []
    # Episodes are written 50 at a time: the two finished before Ctrl-C are written when it comes.
    run_episode = interrupt_collection_at(monkeypatch, 2, calls, write_every=None)
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(spec, progress_bar=False)
    lines = capsys.readouterr().err.splitlines()
    plan = (
        r"collecting sb3cql/Panda-v0/noisy-v0: 4 episodes with 1 worker, about \d+ s and \d+ kB of disk \([\d,]+ transitions\)"
    )
    assert re.fullmatch(plan, lines[0])
    assert lines[1:] == ["interrupted: 2 of 4 episodes of sb3cql/Panda-v0/noisy-v0 kept; the same command resumes"]
    assert not dataset_path("sb3cql/Panda-v0/noisy-v0").exists()
    command = "python -m sb3_cql.data collect --env Panda-v0 --policy noisy --episodes 4 --seed 0"
    with pytest.raises(DatasetError, match=rf"noisy-v0 is partial: .* after 2 of 4 episodes .*resume it with: {command}"):
        load_dataset("sb3cql/Panda-v0/noisy-v0")

    monkeypatch.setattr(collection_module, "_run_episode", lambda index: calls.append(index) or run_episode(index))
    calls.clear()
    resumed = collect_dataset(spec, progress_bar=False)
    assert calls == [2, 3]
    assert capsys.readouterr().err.startswith(
        "resuming sb3cql/Panda-v0/noisy-v0: 2 of 4 episodes already collected; the other 2 with 1 worker, about "
    )
    assert_same_data(resumed, collect_dataset(spec, "sb3cql/Panda-v0/fresh-v0", progress_bar=False))


def test_ctrl_c_that_python_drops_in_a_destructor_still_stops_the_collection(monkeypatch, capsys):
    """A Ctrl-C arriving while a ``__del__`` runs (a garbage-collected PyBullet client disconnecting) raises its
    KeyboardInterrupt there, where Python drops it: the collection stops after the episode anyway."""
    run_episode = collection_module._run_episode

    class Disconnecting:
        def __del__(self):
            signal.raise_signal(signal.SIGINT)  # Ctrl-C now: its KeyboardInterrupt is raised in this __del__,
            for _ in range(3):  # at the loop's first jump back
                pass

    def episode_with_a_collection(index):
        result = run_episode(index)
        if index == 1:
            Disconnecting()  # dropped at once: its __del__ runs here
        return result

    # Ctrl-C as a terminal gives it to a new Python program, whatever earlier tests in this process left behind.
    previous_handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    previous_mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    dropped = []
    monkeypatch.setattr(sys, "unraisablehook", lambda unraisable: dropped.append(unraisable.exc_type))
    monkeypatch.setattr(collection_module, "_run_episode", episode_with_a_collection)
    try:
        with pytest.raises(KeyboardInterrupt):
            collect_dataset(CollectionSpec(policy="random", n_episodes=4), progress_bar=False)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous_mask)
        signal.signal(signal.SIGINT, previous_handler)
    assert dropped == [KeyboardInterrupt]  # Python did drop it
    last_line = capsys.readouterr().err.strip().splitlines()[-1]
    assert last_line == "interrupted: 2 of 4 episodes of sb3cql/Panda-v0/random-v0 kept; the same command resumes"


def test_a_partial_collection_of_another_spec_is_kept_and_the_new_one_refused_until_overwrite(monkeypatch):
    run_episode = interrupt_collection_at(monkeypatch, 1, [])
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(CollectionSpec(policy="random", n_episodes=2), progress_bar=False)
    monkeypatch.setattr(collection_module, "_run_episode", run_episode)
    partial = DatasetFiles("sb3cql/Panda-v0/random-v0")
    command = "python -m sb3_cql.data collect --env Panda-v0 --policy random --episodes 2 --seed 0"
    with pytest.raises(DatasetError, match=rf"is in {re.escape(str(partial.partial))}: 1 of 2 episodes of another "
                                           rf"collection .*resume it with: {command} .*, or pass --overwrite"):  # fmt: skip
        collect_dataset(CollectionSpec(policy="random", n_episodes=1), progress_bar=False)
    assert partial.episodes_held() == 1  # kept
    dataset = collect_dataset(CollectionSpec(policy="random", n_episodes=1), overwrite=True, progress_bar=False)
    assert dataset.total_episodes == 1
    assert dataset.storage.metadata["collection"] == CollectionSpec(policy="random", n_episodes=1).to_json()
    np.testing.assert_array_equal(dataset[0].observations[0], gym.make("Panda-v0").reset(seed=0)[0])
    assert not partial.partial.exists()


def test_mix_combines_datasets():
    collect_dataset(CollectionSpec(n_episodes=2), progress_bar=False)
    collect_dataset(CollectionSpec(policy="random", n_episodes=1), progress_bar=False)
    mixed = mix_datasets(["sb3cql/Panda-v0/pid-v0", "sb3cql/Panda-v0/random-v0"], "sb3cql/Panda-v0/mixed-v0")
    assert mixed.total_episodes == 3
    assert mixed.storage.metadata["success_rate"] == pytest.approx(2 / 3)
    assert mixed.storage.metadata["arrays_sha256"] == arrays_digest(mixed)  # its own arrays', as a collection's
    assert json.loads(mixed.storage.metadata["packages"])["numpy"] == np.__version__
    with pytest.raises(FileExistsError):
        mix_datasets(["sb3cql/Panda-v0/pid-v0"], "sb3cql/Panda-v0/mixed-v0")


def test_fill_replay_buffer_matches_sb3_add():
    dataset = collect_dataset(CollectionSpec(policy="noisy", n_episodes=2), progress_bar=False)
    env = gym.make("Panda-v0")
    buffer = fill_replay_buffer(dataset.spec.dataset_id, env.observation_space, env.action_space)
    assert buffer.size() == dataset.total_steps and buffer.full

    # The same data added one transition at a time, actions scaled by an SB3 policy.
    policy = SAC("MlpPolicy", env, policy_kwargs={"net_arch": [8]}, buffer_size=1).policy
    expected = ReplayBuffer(dataset.total_steps, env.observation_space, env.action_space)
    for episode in dataset.iterate_episodes():
        for t in range(len(episode.rewards)):
            expected.add(
                episode.observations[t],
                episode.observations[t + 1],
                policy.scale_action(episode.actions[t]),
                np.array([episode.rewards[t]]),
                np.array([episode.terminations[t]]),
                [{"TimeLimit.truncated": bool(episode.truncations[t])}],
            )
    for field in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        np.testing.assert_allclose(getattr(buffer, field), getattr(expected, field), rtol=1e-6, atol=1e-6)
    assert buffer.actions.min() >= -1.0 and buffer.actions.max() <= 1.0


def test_fill_replay_buffer_grows_a_small_buffer():
    dataset = collect_dataset(CollectionSpec(n_episodes=1), progress_bar=False)
    env = gym.make("Panda-v0")
    small = ReplayBuffer(10, env.observation_space, env.action_space)
    for value in range(3):
        observation = np.full(29, value, dtype=np.float32)
        small.add(observation, observation, np.zeros(9), np.zeros(1), np.zeros(1), [{}])
    grown = fill_replay_buffer(dataset, env.observation_space, env.action_space, replay_buffer=small)
    assert grown.size() == 3 + dataset.total_steps
    np.testing.assert_array_equal(grown.observations[:3, 0, 0], [0, 1, 2])
    np.testing.assert_array_equal(grown.observations[3:, 0], dataset[0].observations[:-1])


def test_dataset_that_does_not_fit_the_env_is_rejected():
    dataset = collect_dataset(CollectionSpec(n_episodes=1), progress_bar=False)
    pendulum = gym.make("Pendulum-v1")
    with pytest.raises(DatasetError, match="sb3cql/Panda-v0/pid-v0.*shape"):
        fill_replay_buffer(dataset, pendulum.observation_space, pendulum.action_space)
    delta = gym.make("Panda-v0", action_mode="delta")
    with pytest.raises(DatasetError, match="action bounds"):
        fill_replay_buffer(dataset, delta.observation_space, delta.action_space)


def test_missing_dataset_is_named_in_the_error():
    with pytest.raises(DatasetError, match="sb3cql/Panda-v0/nothing-v0 not found"):
        load_dataset("sb3cql/Panda-v0/nothing-v0")


def test_standard_ids_give_their_episodes_in_thousands():
    from sb3_cql.data import standard_collection
    from sb3_cql.data.ids import dataset_id, parse_dataset_id

    assert parse_dataset_id("sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0") == ("Panda-v0", "noisy-regrasp", "delta", 0, 1000)
    assert parse_dataset_id("sb3cql/Panda-v0/pid-v0") == ("Panda-v0", "pid", "absolute", 0, 10_000)
    for policy in ("pid-regrasp-yaw", "noisy-regrasp-yaw"):  # names that begin with another policy's
        yaw_id = f"sb3cql/PandaForce-v0/{policy}-delta-1k-v0"
        assert parse_dataset_id(yaw_id) == ("PandaForce-v0", policy, "delta", 0, 1000)
        assert standard_collection(yaw_id).controller == "pid-regrasp-yaw"
    assert parse_dataset_id("sb3cql/PandaForce-v0/pid-regrasp-aligned-v0") is None  # a reference, never collected
    assert standard_collection("sb3cql/PandaForce-v0/pid-regrasp-aligned-v0") is None
    for not_standard in ("sb3cql/Panda-v0/pid-0k-v0", "sb3cql/Panda-v0/pid-1.5k-v0", "sb3cql/Panda-v0/pid-k-v0"):
        assert parse_dataset_id(not_standard) is None
    assert dataset_id("Panda-v0", "noisy-regrasp", "delta", episodes=1000) == "sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0"
    assert dataset_id("Panda-v0", "pid", episodes=10_000) == "sb3cql/Panda-v0/pid-v0"
    with pytest.raises(ValueError, match="thousands"):
        dataset_id("Panda-v0", "pid", episodes=1500)
    # A -<N>k dataset is the first N thousand episodes of the standard one: the same spec but for their number.
    small, full = (standard_collection(f"sb3cql/PandaForce-v0/noisy-regrasp-delta{size}-v0") for size in ("-2k", ""))
    assert (small.n_episodes, full.n_episodes) == (2000, 10_000)
    assert dataclasses.replace(small, n_episodes=10_000) == full
    assert full.env_id == "PandaForce-v0" and full.action_mode == "delta" and full.seed == 0
    assert standard_collection("sb3cql/Panda-v0/pid-v1") is None and standard_collection("sb3cql/Nope-v0/pid-v0") is None
    # The command line's default id says how many episodes a collection holds.
    assert collect_dataset(CollectionSpec(n_episodes=1), progress_bar=False).spec.dataset_id == "sb3cql/Panda-v0/pid-v0"


def test_missing_standard_dataset_is_collected_once(capsys):
    dataset = ensure_dataset("sb3cql/Panda-v0/pid-delta-v0", n_episodes=2, workers=1, progress_bar=False)
    (line,) = capsys.readouterr().err.splitlines()
    plan = r"collecting sb3cql/Panda-v0/pid-delta-v0: 2 episodes with 1 worker, about \d+ s and (\d+) kB of disk "
    plan += r"\(356 transitions\)"
    estimated_size = int(re.fullmatch(plan, line).group(1)) * 1000
    size = sum(file.stat().st_size for file in dataset_path("sb3cql/Panda-v0/pid-delta-v0").rglob("*") if file.is_file())
    assert abs(estimated_size - size) < 0.2 * size  # the disk estimate is a fair one
    metadata = dataset.storage.metadata
    assert dataset.total_episodes == 2 and metadata["dataset_id"] == "sb3cql/Panda-v0/pid-delta-v0"
    assert dataset.recover_environment().unwrapped.action_mode == "delta"
    assert ensure_dataset("sb3cql/Panda-v0/pid-delta-v0", n_episodes=3).total_episodes == 2  # found, not collected again
    for unknown in ("sb3cql/Panda-v0/mixed-v0", "sb3cql/Panda-v0/pid-v1", "sb3cql/Nothing-v0/pid-v0", "other/x-v0"):
        with pytest.raises(DatasetError, match="not found"):
            ensure_dataset(unknown, n_episodes=1)


def test_truncated_dataset_file_is_reported():
    dataset = collect_dataset(CollectionSpec(n_episodes=2), progress_bar=False)
    data_file = dataset.storage.data_path / "main_data.hdf5"
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    with pytest.raises(DatasetError, match="truncated or corrupt"):
        load_dataset("sb3cql/Panda-v0/pid-v0")


@pytest.mark.parametrize(
    "field, step, value, message",
    [
        ("observations", 2, np.nan, r"episode 0, step 2: observation\[28\] is nan, not finite$"),
        ("rewards", 1, np.inf, r"episode 0, step 1: reward is inf, not finite$"),
        ("actions", 1, np.nan, r"episode 0, step 1: action\[8\] is nan, not finite$"),
        (
            "actions",
            2,
            1.0,
            r"episode 0, step 2: action\[8\] is 1, outside the action space's bounds \[0, 0.04\] "
            r"\(data of another action mode\?\)",
        ),
    ],
)
def test_non_finite_values_and_actions_outside_the_action_space_are_refused_naming_episode_and_step(
    field, step, value, message
):
    env = gym.make("Panda-v0")
    space = env.action_space
    arrays = {
        "observations": np.zeros((4, 29), dtype=np.float32),
        "actions": np.tile((space.low + space.high) / 2, (3, 1)).astype(np.float32),
        "rewards": np.zeros(3),
    }
    if field == "rewards":
        arrays[field][step] = value
    else:
        arrays[field][step, -1] = value  # the gripper's action: 1.0 lies far beyond its 0.04 bound
    episode = minari.data_collector.EpisodeBuffer(
        **arrays, terminations=np.zeros(3, dtype=bool), truncations=np.array([False, False, True])
    )
    minari.create_dataset_from_buffers("sb3cql/Panda-v0/bad-v0", [episode], env=env, algorithm_name="test", author="t",
                                       author_email="t", code_permalink="t", description="t")  # fmt: skip
    with pytest.raises(DatasetError, match=message):
        fill_replay_buffer("sb3cql/Panda-v0/bad-v0", env.observation_space, env.action_space)


def test_command_line_collects_and_describes(capsys):
    data_cli(["collect", "--policy", "random", "--episodes", "1", "--seed", "3", "--dataset-id", "sb3cql/Panda-v0/rnd-v0"])
    assert "sb3cql/Panda-v0/rnd-v0: 1 episodes, 700 transitions" in capsys.readouterr().out
    data_cli(["info", "sb3cql/Panda-v0/rnd-v0"])
    assert '"success_rate": 0.0' in capsys.readouterr().out


def test_killed_worker_stops_the_collection_with_a_clear_error(minari_root):
    import multiprocessing
    import threading

    spec = CollectionSpec(policy="noisy", n_episodes=60)
    outcome = {}

    def collect():
        try:
            collect_dataset(spec, workers=2, progress_bar=False)
        except Exception as error:  # noqa: BLE001  (the error is the test's subject)
            outcome["error"] = error

    thread = threading.Thread(target=collect)
    thread.start()
    deadline = time.monotonic() + 60
    while len(multiprocessing.active_children()) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(3.0)  # let the workers start episodes
    os.kill(multiprocessing.active_children()[0].pid, signal.SIGKILL)
    thread.join(timeout=60)
    assert not thread.is_alive(), "the collection hung after a worker was killed"
    assert isinstance(outcome.get("error"), RuntimeError) and "worker died" in str(outcome["error"])
    assert not dataset_path("sb3cql/Panda-v0/noisy-v0").exists()


def run_data_cli(args: list[str], minari_root, **kwargs) -> subprocess.Popen:
    """Start ``python -m sb3_cql.data ARGS`` in a process group of its own, as a terminal would."""
    env = {**os.environ, "MINARI_DATASETS_PATH": str(minari_root)}
    command = [sys.executable, "-m", "sb3_cql.data", *args]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, **kwargs)


def test_ctrl_c_stops_the_command_line_collection_and_the_same_command_resumes(minari_root):
    args = ["collect", "--policy", "pid", "--episodes", "30", "--workers", "2", "--write-every", "2"]
    process = run_data_cli(args, minari_root, start_new_session=True)
    partial = DatasetFiles("sb3cql/Panda-v0/pid-v0")
    try:
        while process.poll() is None and partial.episodes_held() < 2:  # until the first 2 episodes are on disk
            time.sleep(0.05)
        assert process.poll() is None, "the collection ended before it could be interrupted"
        os.killpg(process.pid, signal.SIGINT)  # Ctrl-C: to the command and its workers
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)

    assert process.returncode == 130
    assert "Traceback" not in stderr and stdout == ""
    assert "argv[0]=" not in stderr and "pybullet build time" not in stderr  # nor from PyBullet in the workers
    (interrupted,) = [line for line in stderr.splitlines() if "interrupted" in line]
    kept = int(
        re.fullmatch(
            r"interrupted: (\d+) of 30 episodes of sb3cql/Panda-v0/pid-v0 kept; the same command resumes", interrupted
        )[1]
    )
    assert 2 <= kept < 30 and partial.episodes_held() == kept
    assert not dataset_path("sb3cql/Panda-v0/pid-v0").exists()

    rerun = run_data_cli(args, minari_root)
    stdout, stderr = rerun.communicate(timeout=120)
    assert rerun.returncode == 0, stderr
    assert "argv[0]=" not in stdout + stderr and "pybullet build time" not in stdout + stderr
    assert (
        f"resuming sb3cql/Panda-v0/pid-v0: {kept} of 30 episodes already collected; the other {30 - kept} with 2 workers"
        in stderr
    )
    assert stdout.startswith("sb3cql/Panda-v0/pid-v0: 30 episodes")
    fresh = collect_dataset(CollectionSpec(n_episodes=30), "sb3cql/Panda-v0/fresh-v0", progress_bar=False)
    assert_same_data(load_dataset("sb3cql/Panda-v0/pid-v0"), fresh)


def test_command_line_errors_are_one_line_with_status_2(monkeypatch, capsys, tmp_path):
    def error_of(args: list[str]) -> str:
        capsys.readouterr()
        with pytest.raises(SystemExit) as exit_info:
            data_cli(args)
        assert exit_info.value.code == 2
        return capsys.readouterr().err

    def one_line(args: list[str]) -> str:
        (line,) = error_of(args).splitlines()
        assert line.startswith(
            "python -m sb3_cql.data: error: dataset " if "info" in args else "python -m sb3_cql.data: error: "
        )
        return line

    assert "sb3cql/Panda-v0/nothing-v0 not found" in one_line(["info", "sb3cql/Panda-v0/nothing-v0"])
    assert "sb3cql/Panda-v0/nothing-v0 not found" in one_line(
        ["mix", "--dataset-id", "sb3cql/Panda-v0/mixed-v0", "sb3cql/Panda-v0/nothing-v0"]
    )

    run_episode = interrupt_collection_at(monkeypatch, 1, [])
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(CollectionSpec(policy="random", n_episodes=3), progress_bar=False)
    monkeypatch.setattr(collection_module, "_run_episode", run_episode)
    partial = one_line(["info", "sb3cql/Panda-v0/random-v0"])
    assert "random-v0 is partial: its collection was interrupted after 1 of 3 episodes" in partial
    assert "resume it with: python -m sb3_cql.data collect --env Panda-v0 --policy random --episodes 3" in partial

    collect_dataset(CollectionSpec(n_episodes=1), progress_bar=False)
    assert "already exists" in one_line(["collect", "--episodes", "1"])
    data_file = dataset_path("sb3cql/Panda-v0/pid-v0") / "data" / "main_data.hdf5"
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    assert "truncated or corrupt" in one_line(["info", "sb3cql/Panda-v0/pid-v0"])

    assert "invalid choice: 'Nothing-v0'" in error_of(["collect", "--env", "Nothing-v0"])
    model = tmp_path / "model.zip"
    model.write_bytes(b"not a model")
    assert f"cannot load {model} as a sac model" in one_line(["collect", "--policy", str(model), "--algo", "sac"])
    assert "unknown algo 'nothing'" in one_line(["collect", "--policy", str(model), "--algo", "nothing"])
    assert not dataset_path("sb3cql/Panda-v0/model-v0").exists()


def test_command_line_error_has_no_traceback(minari_root):
    process = run_data_cli(["info", "sb3cql/Panda-v0/nothing-v0"], minari_root)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 2 and stdout == ""
    assert stderr.startswith("python -m sb3_cql.data: error: dataset sb3cql/Panda-v0/nothing-v0 not found")
    assert len(stderr.splitlines()) == 1
