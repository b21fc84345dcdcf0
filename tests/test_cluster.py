"""Work on a real Ray cluster of two nodes started on this machine: collections through ``--ray``."""

import os
import subprocess
import sys

import numpy as np
import pytest

from sb3_cql.data import CollectionSpec, collect_dataset, load_dataset
from sb3_cql.data.partial import DatasetFiles

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
