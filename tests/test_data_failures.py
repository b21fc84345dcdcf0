"""What survives what in a collection: real kills at every moment, SIGTERM, two collections at once, a full disk, a
read-only folder, damaged files, and models of another action mode."""

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import minari
import numpy as np
import pytest
from minari.dataset.minari_storage import MinariStorage
from stable_baselines3 import SAC

from sb3_cql.data import CollectionSpec, DatasetError, collect_dataset, dataset_path, ensure_dataset, load_dataset
from sb3_cql.data import collection as collection_module
from sb3_cql.data.ids import SPEC_FILE
from sb3_cql.data.store import CRASH_AT_ENV, CRASH_POINTS, DatasetFiles

DATASET = "sb3cql/Panda-v0/pid-v0"
#: A collection small enough to run many times: 4 PD episodes of ~178 steps, 2 to a file.
COMMAND = ["collect", "--policy", "pid", "--episodes", "4", "--write-every", "2"]


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    return tmp_path / "datasets"


def assert_same_data(first, second):
    assert first.total_episodes == second.total_episodes
    for a, b in zip(first.iterate_episodes(), second.iterate_episodes(), strict=True):
        for field in ("observations", "actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        np.testing.assert_array_equal((a.infos or {}).get("clean_action", []), (b.infos or {}).get("clean_action", []))
    assert first.storage.metadata["collection"] == second.storage.metadata["collection"]
    assert first.storage.metadata["success_rate"] == second.storage.metadata["success_rate"]


def reference(spec: CollectionSpec):
    """The dataset an uninterrupted collection of ``spec`` gives, under another id."""
    return collect_dataset(spec, "sb3cql/Panda-v0/reference-v0", progress_bar=False)


def start_cli(args, minari_root, crash_at=None, **kwargs) -> subprocess.Popen:
    env = {**os.environ, "MINARI_DATASETS_PATH": str(minari_root)}
    env.pop(CRASH_AT_ENV, None)
    if crash_at is not None:
        env[CRASH_AT_ENV] = crash_at
    command = [sys.executable, "-m", "sb3_cql.data", *args]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, **kwargs)


def run_cli(args, minari_root, crash_at=None, timeout=120) -> subprocess.CompletedProcess:
    process = start_cli(args, minari_root, crash_at)
    stdout, stderr = process.communicate(timeout=timeout)
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


def leftovers(minari_root: Path) -> list[str]:
    """Hidden folders a collection of DATASET leaves beside it (the lock file is kept on purpose)."""
    folder = dataset_path(DATASET).parent
    return sorted(path.name for path in folder.iterdir() if path.name.startswith(".") and path.is_dir())


def wait_for(condition, process: subprocess.Popen, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert process.poll() is None, f"the collection ended first: {process.communicate()}"
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def group_members(pgid: int) -> list[int]:
    """The live (not zombie) processes of the process group ``pgid``."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid and fields[0] != "Z":
                members.append(int(stat.parent.name))
    return members


def group_gone(pgid: int, timeout: float = 15) -> bool:
    """Whether every process of the group ``pgid`` has ended within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not group_members(pgid):
            return True
        time.sleep(0.1)
    return False


@pytest.mark.parametrize("point", CRASH_POINTS)
def test_a_kill_at_any_point_of_a_collection_resumes_to_the_dataset_an_uninterrupted_one_gives(minari_root, point):
    """A collection replacing an older dataset (``--overwrite``) is killed with SIGKILL at ``point``; meanwhile the id
    reads as one complete dataset, and the same command ends in the dataset of an uninterrupted collection."""
    old = collect_dataset(CollectionSpec(n_episodes=3), progress_bar=False)
    old_observations = old[0].observations.copy()
    killed = run_cli([*COMMAND, "--overwrite"], minari_root, crash_at=point)
    assert killed.returncode == -signal.SIGKILL, killed.stderr

    between = load_dataset(DATASET)  # the old dataset, or (once the swap began) the new one: never none
    first = between[0].observations
    expected = reference(CollectionSpec(n_episodes=4))
    if between.total_episodes == 3:
        np.testing.assert_array_equal(first, old_observations)
    else:
        assert_same_data(between, expected)

    rerun = run_cli([*COMMAND, "--overwrite"], minari_root)
    assert rerun.returncode == 0, rerun.stderr
    assert_same_data(load_dataset(DATASET), expected)
    assert leftovers(minari_root) == []


def test_kills_at_moments_chosen_by_time_lose_nothing(minari_root):
    args = ["collect", "--policy", "pid", "--episodes", "12", "--write-every", "1"]
    files = DatasetFiles(DATASET)
    for kill in range(4):  # each kill lands a little later in the collection
        process = start_cli(args, minari_root)
        held = files.episodes_held()
        wait_for(lambda held=held: files.episodes_held() > held, process)
        time.sleep(0.05 * kill)
        process.kill()
        process.communicate(timeout=60)
        if process.returncode == 0:
            break
    final = run_cli(args, minari_root)
    assert final.returncode == 0, final.stderr
    assert_same_data(load_dataset(DATASET), reference(CollectionSpec(n_episodes=12)))
    assert leftovers(minari_root) == []


def test_sigterm_ends_a_collection_like_ctrl_c_and_a_killed_one_takes_its_workers_along(minari_root):
    args = ["collect", "--policy", "pid", "--episodes", "40", "--workers", "2", "--write-every", "2"]
    files = DatasetFiles(DATASET)

    process = start_cli(args, minari_root, start_new_session=True)
    wait_for(lambda: files.episodes_held() >= 2, process)
    process.terminate()  # SIGTERM to the command only, as `kill PID` sends it
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 143 and "Traceback" not in stderr, stderr
    (line,) = [line for line in stderr.splitlines() if "interrupted" in line]
    kept = int(re.fullmatch(rf"interrupted: (\d+) of 40 episodes of {DATASET} kept; the same command resumes", line)[1])
    assert kept == files.episodes_held() >= 2
    assert group_gone(process.pid), "the workers outlived the command"

    process = start_cli(args, minari_root, start_new_session=True)
    wait_for(lambda: files.episodes_held() >= kept + 2, process)
    process.kill()
    process.communicate(timeout=60)
    assert group_gone(process.pid), "the workers outlived the killed command"

    rerun = run_cli(args, minari_root)
    assert rerun.returncode == 0, rerun.stderr
    assert_same_data(load_dataset(DATASET), reference(CollectionSpec(n_episodes=40)))


def test_a_second_collection_of_the_same_id_is_refused_while_one_runs(minari_root):
    args = ["collect", "--policy", "pid", "--episodes", "200", "--write-every", "1"]
    files = DatasetFiles(DATASET)
    first = start_cli(args, minari_root)
    try:
        wait_for(lambda: files.episodes_held() >= 1, first)
        second = run_cli(args, minari_root)
        assert second.returncode == 2 and "Traceback" not in second.stderr
        assert second.stderr.splitlines() == [
            f"python -m sb3_cql.data: error: dataset {DATASET} is being written by another process (pid {first.pid}, "
            f"which holds {files.lock_file}): wait for it to end, or stop it and run the command again"
        ]
        assert first.poll() is None  # the first goes on
    finally:
        first.kill()
        first.communicate(timeout=60)


def test_a_collection_written_before_episode_files_resumes_from_what_its_data_file_holds(minari_root):
    """A kill between the data file's write and its metadata.json left a count behind the file (or metadata.json
    half written): the episodes the file holds are read whole and kept."""
    spec = CollectionSpec(n_episodes=5)
    files = DatasetFiles(DATASET)
    env = gym.make("Panda-v0")
    files.partial.mkdir(parents=True)
    storage = MinariStorage.new(files.storage_before_episode_files, env.observation_space, env.action_space, env.spec,
                                data_format="hdf5")  # fmt: skip
    collection_module._init_worker(spec)
    try:
        storage.update_episodes([collection_module._run_episode(index) for index in range(3)])
    finally:
        collection_module._worker["env"].close()
        collection_module._worker.clear()
    (files.partial / SPEC_FILE).write_text(spec.to_json())
    metadata = files.storage_before_episode_files / "metadata.json"
    metadata.write_text(metadata.read_text()[:40])  # half written

    calls = []
    run_episode = collection_module._run_episode
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(collection_module, "_run_episode", lambda index: calls.append(index) or run_episode(index))
        dataset = collect_dataset(spec, progress_bar=False)
    assert calls == [3, 4]
    assert_same_data(dataset, reference(spec))


def test_a_damaged_episode_file_is_refused_saying_what_is_readable(minari_root, monkeypatch):
    spec = CollectionSpec(policy="random", n_episodes=6)
    files = DatasetFiles("sb3cql/Panda-v0/random-v0")
    run_episode = collection_module._run_episode

    def interrupted_after_four(index):
        if index == 4:
            raise KeyboardInterrupt
        return run_episode(index)

    monkeypatch.setattr(collection_module, "_run_episode", interrupted_after_four)
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(spec, progress_bar=False, write_every=2)
    monkeypatch.setattr(collection_module, "_run_episode", run_episode)
    (_, first), (_, second) = files.episode_files()
    second.write_bytes(second.read_bytes()[:100])
    with pytest.raises(DatasetError, match=rf"has a damaged file {second.name} \(episodes 2-3: .*\); its other 2 episodes "
                                           rf"are readable: remove {re.escape(str(second))} to collect its episodes "
                                           r"again, or pass --overwrite"):  # fmt: skip
        collect_dataset(spec, progress_bar=False)
    assert first.exists() and second.exists()  # nothing removed
    second.unlink()
    assert_same_data(collect_dataset(spec, progress_bar=False), reference(spec))


def test_a_dataset_without_its_metadata_gets_the_same_answer_from_info_collect_and_ensure(minari_root):
    dataset_id = "sb3cql/Panda-v0/pid-1k-v0"
    collect_dataset(CollectionSpec(policy="pid", n_episodes=2), dataset_id, progress_bar=False)
    (dataset_path(dataset_id) / "data" / "metadata.json").unlink()
    expected = (
        f"dataset {dataset_id} at {dataset_path(dataset_id)} is damaged: it has no data/metadata.json and cannot be "
        f"read; replace it with: python -m sb3_cql.data collect --env Panda-v0 --policy pid --episodes 1000 --seed 0 "
        f"--dataset-id {dataset_id} --overwrite"
    )
    for args in (["info", dataset_id], ["collect", "--episodes", "1000", "--dataset-id", dataset_id]):
        answer = run_cli(args, minari_root)
        assert answer.returncode == 2 and answer.stderr.splitlines() == [f"python -m sb3_cql.data: error: {expected}"]
    with pytest.raises(DatasetError) as error:
        ensure_dataset(dataset_id)  # what the zoo calls
    assert str(error.value) == expected


def test_a_model_collects_in_its_own_action_mode(minari_root, tmp_path):
    model = tmp_path / "delta model.zip"
    SAC("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), policy_kwargs={"net_arch": [8]}, buffer_size=1).save(model)
    args = ["collect", "--policy", str(model), "--algo", "sac", "--episodes", "1", "--dataset-id", "sb3cql/Panda-v0/model-v0"]

    refused = run_cli([*args, "--action-mode", "absolute"], minari_root)
    assert refused.returncode == 2 and len(refused.stderr.splitlines()) == 1
    assert "is that of action_mode 'delta', not that of the action_mode 'absolute' asked for" in refused.stderr
    with pytest.raises(ValueError, match="is that of action_mode 'delta'"):
        collect_dataset(
            CollectionSpec(policy=str(model), algo="sac", n_episodes=1), "sb3cql/Panda-v0/model-v0", progress_bar=False
        )

    collected = run_cli(args, minari_root)
    assert collected.returncode == 0, collected.stderr
    dataset = load_dataset("sb3cql/Panda-v0/model-v0")
    assert json.loads(dataset.storage.metadata["env_kwargs"])["action_mode"] == "delta"
    assert np.all(np.abs(dataset[0].actions) <= 1.0)


def test_ctrl_c_while_the_command_line_starts_is_one_line(minari_root):
    process = start_cli(["info", DATASET], minari_root)
    maps = Path(f"/proc/{process.pid}/maps")
    if not maps.exists():
        process.kill()
        pytest.skip("needs /proc to see when the start-up imports begin")
    # numpy's extension is loaded by the command's first imports, after it set its handler
    wait_for(lambda: "_multiarray_umath" in maps.read_text(), process, timeout=30)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 130
    assert stderr.splitlines() == ["python -m sb3_cql.data: interrupted while starting: nothing done"]


# Disks that fill and folders that cannot be written: a small tmpfs of their own (root only).


@contextlib.contextmanager
def small_disk(path: Path, size: str):
    path.mkdir(parents=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {mounted.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def test_a_disk_without_room_is_refused_before_the_collection_starts(tmp_path):
    with small_disk(tmp_path / "disk", "1m") as disk:
        refused = run_cli(["collect", "--policy", "pid", "--episodes", "20"], disk)
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        (line,) = refused.stderr.splitlines()[-1:]
        assert re.fullmatch(
            rf"python -m sb3_cql.data: error: not enough disk space in {re.escape(str(disk))}/sb3cql/Panda-v0 for 20 "
            r"episodes and the dataset's assembly: about [\d.]+ [kMG]B needed, [\d.]+ [kMG]B free; free some space .*",
            line,
        )
        assert DatasetFiles(DATASET).episodes_held() == 0


def test_a_disk_that_fills_during_a_collection_keeps_what_was_written_and_resumes(tmp_path, monkeypatch):
    args = ["collect", "--policy", "pid", "--episodes", "30", "--write-every", "1"]
    with small_disk(tmp_path / "disk", "8m") as disk:
        monkeypatch.setenv("MINARI_DATASETS_PATH", str(disk))
        files = DatasetFiles(DATASET)
        process = start_cli(args, disk)
        wait_for(lambda: files.episodes_held() >= 1, process)
        filler = disk / "filler"
        with open(filler, "wb", buffering=0) as file, contextlib.suppress(OSError):
            while True:
                file.write(b"\0" * (1 << 16))
        stdout, stderr = process.communicate(timeout=60)
        assert process.returncode == 2 and "Traceback" not in stderr, stderr
        line = stderr.splitlines()[-1]
        kept = int(re.search(r"the (\d+) episodes written before are kept", line)[1])
        assert line.startswith(f"python -m sb3_cql.data: error: no space left in {disk}/sb3cql/Panda-v0 for episodes ")
        assert "free some space and run the same command to resume" in line and kept == files.episodes_held() >= 1

        filler.unlink()
        rerun = run_cli(args, disk)
        assert rerun.returncode == 0, rerun.stderr
        assert f"resuming {DATASET}: {kept} of 30 episodes already collected" in rerun.stderr
        assert_same_data(load_dataset(DATASET), reference(CollectionSpec(n_episodes=30)))


def test_a_read_only_collection_is_refused_before_any_episode(tmp_path, monkeypatch):
    args = ["collect", "--policy", "pid", "--episodes", "6", "--write-every", "1"]
    with small_disk(tmp_path / "disk", "8m") as disk:
        monkeypatch.setenv("MINARI_DATASETS_PATH", str(disk))
        files = DatasetFiles(DATASET)
        process = start_cli(args, disk)
        wait_for(lambda: files.episodes_held() >= 1, process)
        process.send_signal(signal.SIGINT)
        process.communicate(timeout=60)
        held = files.episodes_held()
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        try:
            refused = run_cli(args, disk)
        finally:
            subprocess.run(["mount", "-o", "remount,rw", str(disk)], check=True)
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        assert refused.stderr.splitlines() == [
            f"python -m sb3_cql.data: error: cannot write dataset {DATASET} in {disk}/sb3cql/Panda-v0: Read-only file system"
        ]
        assert files.episodes_held() == held
        assert run_cli(args, disk).returncode == 0
        assert_same_data(load_dataset(DATASET), reference(CollectionSpec(n_episodes=6)))


def test_minari_reads_a_resumed_dataset(minari_root):
    """The assembled dataset is Minari's own: another library's ``minari.load_dataset`` reads it."""
    killed = run_cli(COMMAND, minari_root, crash_at="assemble")
    assert killed.returncode == -signal.SIGKILL
    assert run_cli(COMMAND, minari_root).returncode == 0
    dataset = minari.load_dataset(DATASET)
    assert dataset.total_episodes == 4 and dataset.storage.metadata["success_rate"] == 1.0


def test_a_standard_dataset_that_another_process_collects_is_waited_for_and_loaded(minari_root, capsys):
    """Two trainings started at once on a new machine: the second waits for the first's collection."""
    dataset_id = "sb3cql/Panda-v0/pid-1k-v0"
    code = f"from sb3_cql.data import ensure_dataset; ensure_dataset({dataset_id!r}, n_episodes=30, workers=1)"
    files = DatasetFiles(dataset_id)
    env = {**os.environ, "MINARI_DATASETS_PATH": str(minari_root)}
    first = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_for(lambda: files.episodes_held() >= 1, first)
        dataset = ensure_dataset(dataset_id, n_episodes=30, progress_bar=False)
        assert first.wait(timeout=120) == 0
    finally:
        if first.poll() is None:
            first.kill()
        first.communicate()
    assert f"waiting for the collection of {dataset_id} by another process (pid {first.pid}) to end" in (
        capsys.readouterr().err
    )
    assert dataset.total_episodes == 30
    assert_same_data(dataset, reference(CollectionSpec(policy="pid", n_episodes=30)))
