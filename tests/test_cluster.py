"""Work on a real Ray cluster of two nodes started on this machine: collections and the protocol through ``--ray``."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sb3_cql.data import CollectionSpec, collect_dataset, load_dataset
from sb3_cql.data.store import DatasetFiles


@pytest.fixture(scope="module")
def cluster():
    """A head and a worker node of one CPU each: tasks run in the nodes' own worker processes."""
    cluster_utils = pytest.importorskip("ray.cluster_utils", reason="the Ray extra is not installed: pip install -e '.[ray]'")
    cluster = cluster_utils.Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    yield cluster
    cluster.shutdown()


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    return tmp_path / "datasets"


def data_cli(args, minari_root, **kwargs):
    env = {**os.environ, "MINARI_DATASETS_PATH": str(minari_root)}
    return subprocess.run([sys.executable, "-m", "sb3_cql.data", *args], capture_output=True, text=True, env=env,
                          timeout=300, **kwargs)  # fmt: skip


def assert_same_data(first, second):
    assert first.total_episodes == second.total_episodes
    for a, b in zip(first.iterate_episodes(), second.iterate_episodes(), strict=True):
        for field in ("observations", "actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        np.testing.assert_array_equal(a.infos["clean_action"], b.infos["clean_action"])
    assert first.storage.metadata["collection"] == second.storage.metadata["collection"]


def test_a_collection_on_ray_is_the_local_one_and_an_interrupted_one_resumes(cluster, minari_root):
    args = ["collect", "--policy", "noisy", "--episodes", "6", "--write-every", "2", "--ray", cluster.address]
    env = {**os.environ, "MINARI_DATASETS_PATH": str(minari_root), "SB3_CQL_CRASH_AT": "episodes-written"}
    first = subprocess.run([sys.executable, "-m", "sb3_cql.data", *args], capture_output=True, text=True, env=env,
                           timeout=300)  # fmt: skip
    assert first.returncode == -9, first.stderr  # killed as its first file was about to be renamed
    assert "as Ray tasks on the 2 CPUs of the cluster at" in first.stderr

    resumed = data_cli(args, minari_root)
    assert resumed.returncode == 0, resumed.stderr
    local = collect_dataset(CollectionSpec(policy="noisy", n_episodes=6), "sb3cql/Panda-v0/local-v0", workers=2,
                            progress_bar=False)  # fmt: skip
    assert_same_data(load_dataset("sb3cql/Panda-v0/noisy-v0"), local)
    assert not DatasetFiles("sb3cql/Panda-v0/noisy-v0").partial.exists()


def test_ray_missing_is_one_line_saying_how_to_install_it(minari_root):
    code = ("import sys; sys.modules['ray'] = None; from sb3_cql.data.__main__ import main; "
            "main(['collect', '--episodes', '2', '--ray', 'auto'])")  # fmt: skip
    env = {**os.environ, "MINARI_DATASETS_PATH": str(minari_root)}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1:] == [
        "python -m sb3_cql.data: error: --ray needs Ray, which is not installed: "
        'pip install -e ".[ray]" (or pip install "ray>=2.60")'
    ]


# The protocol: a tiny BC one (1 seed, 300 steps, 2 evaluation episodes a task) on a 4-episode dataset.
PROTOCOL = ["--algos", "bc", "--seeds", "1", "--n-timesteps", "300", "--eval-freq", "300", "--eval-episodes", "1",
            "--episodes", "2", "--save-freq", "100", "--no-filmstrips",
            "--zoo-args", "--hyperparams batch_size:64 policy_kwargs:dict(net_arch=[32,32])"]  # fmt: skip
TIMES = {"train_wall_time_s", "eval_wall_time_s"}


def benchmark(args, root, **kwargs):
    env = {**os.environ, "MINARI_DATASETS_PATH": str(root / "datasets"), "MPLBACKEND": "Agg"}
    return subprocess.Popen([sys.executable, "-m", "sb3_cql.protocol", *PROTOCOL, *args], cwd=root, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)  # fmt: skip


def records(results):
    """Every record of a results folder, without its wall times."""
    found = {}
    for path in sorted((results / "records").rglob("*.json")):
        record = json.loads(path.read_text())
        found[str(path.relative_to(results))] = {key: value for key, value in record.items() if key not in TIMES}
    return found


@pytest.fixture(scope="module")
def protocol_root(tmp_path_factory, cluster):
    root = tmp_path_factory.mktemp("protocol")
    collect = subprocess.run([sys.executable, "-m", "sb3_cql.data", "collect", "--policy", "noisy-regrasp",
                              "--action-mode", "delta", "--episodes", "4", "--dataset-id",
                              "sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0"],
                             env={**os.environ, "MINARI_DATASETS_PATH": str(root / "datasets")}, capture_output=True,
                             text=True, timeout=300)  # fmt: skip
    assert collect.returncode == 0, collect.stderr
    return root


@pytest.mark.slow  # two protocol runs side by side (a minute); the Ray collection test above covers the cluster in CI
def test_the_protocol_on_ray_records_what_it_records_locally(cluster, protocol_root):
    local = benchmark(["--workers", "2", "--results-dir", "local"], protocol_root)
    on_ray = benchmark(["--ray", cluster.address, "--results-dir", "ray"], protocol_root)
    for process in (local, on_ray):
        stdout, stderr = process.communicate(timeout=900)
        assert process.returncode == 0, f"{stdout[-2000:]}\n{stderr[-2000:]}"
    expected = records(protocol_root / "local")
    assert len(expected) == 4  # a training and an evaluation on each of the 3 tasks
    assert records(protocol_root / "ray") == expected


def zoo_parents(results) -> list[int]:
    """The processes running a zoo training of ``results``: the parents of its ``rl_zoo3.train`` processes."""
    parents = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            command = (proc / "cmdline").read_bytes().split(b"\0")
            if b"rl_zoo3.train" in command and any(str(results).encode() in part for part in command):
                parents.append(int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1]))
        except (OSError, IndexError, ValueError):
            continue
    return parents


@pytest.mark.slow
def test_a_ray_worker_killed_mid_unit_leaves_no_half_record_and_the_unit_completes(cluster, protocol_root):
    results = protocol_root / "killed"
    process = benchmark(["--ray", cluster.address, "--results-dir", "killed"], protocol_root)
    deadline = time.monotonic() + 300
    while not zoo_parents(results):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.1)
    (worker,) = set(zoo_parents(results))
    os.kill(worker, signal.SIGKILL)  # the Ray worker running the training: its zoo run dies with it
    stdout, stderr = process.communicate(timeout=900)
    assert process.returncode == 0, f"{stdout[-2000:]}\n{stderr[-2000:]}"
    found = records(results)  # every record reads as whole JSON
    assert len(found) == 4
    (training,) = [record for name, record in found.items() if "/train/" in name]
    assert training["training_steps"] == 300
