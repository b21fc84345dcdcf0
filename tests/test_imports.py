"""The algorithms import without the simulator, the zoo or the plotting libraries; the collection loads when a
standard dataset must be made."""

import subprocess
import sys

import pytest

#: What an algorithm import must not load: the tasks and their simulator, Minari, the zoo, Optuna, matplotlib.
HEAVY = ("pybullet", "envs", "minari", "rl_zoo3", "optuna", "matplotlib", "sb3_cql.data.collection")


def loaded_after(code: str) -> list[str]:
    """The :data:`HEAVY` modules loaded after ``code`` runs in a fresh interpreter."""
    check = f"{code}; import sys; print([name for name in {HEAVY!r} if name in sys.modules])"
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, check=True)
    return eval(result.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(
    "code",
    ["import sb3_cql", "from sb3_cql import CQL, BC", "from sb3_cql.common import OfflineSAC", "import sb3_cql.cql.policies"],
)
def test_the_algorithms_import_nothing_of_the_simulator_or_the_zoo(code):
    assert loaded_after(code) == []


def test_loading_data_imports_minari_but_not_the_simulator():
    assert loaded_after("from sb3_cql.data import fill_replay_buffer") == ["minari"]


def test_the_collection_is_imported_when_it_is_asked_for():
    loaded = loaded_after("from sb3_cql.data import ensure_dataset, standard_collection")
    assert {"pybullet", "envs", "sb3_cql.data.collection"} <= set(loaded)
