import os
import signal
from collections.abc import Iterator

# One torch thread a process, the tests' and the commands they start (which inherit it): the suite's networks are
# tiny, and two threads a process spend more time waiting on each other than computing, several times more when the
# commands a test starts run beside it on the two cores. A thread count given by the caller is kept.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import postgres
import pytest

import envs

#: The test files by how long they take, longest first (the first two minutes each: they train and evaluate through the
#: zoo and the protocol's commands), so that the suite's two processes (``-n 2 --dist loadfile``, pyproject.toml) end
#: together; the files not named, which take seconds, come last.
LONGEST_FIRST = ("test_protocol.py", "test_zoo.py", "test_cql.py", "test_data_failures.py", "test_cluster.py",
                 "test_data.py", "test_evaluate.py", "test_envs.py", "test_experiments.py", "test_sb3_contracts.py",
                 "test_imports.py", "test_bad_input.py", "test_docs.py")  # fmt: skip


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: position for position, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # a stable sort: each file keeps its own order


@pytest.fixture(autouse=True, scope="session")
def one_torch_thread() -> None:
    """Torch's threads as ``OMP_NUM_THREADS`` says (torch reads it when it is first imported, which may have been
    before this file)."""
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


@pytest.fixture(autouse=True, scope="session")
def children_take_ctrl_c() -> None:
    """The processes the tests start get Ctrl-C's default disposition, unblocked, however pytest was started: a shell
    script's ``python -m pytest &`` (no job control) starts it with SIGINT ignored, which children would inherit
    through ``exec``, and then the tests that send them SIGINT would wait on processes that never see it. A Python
    handler in pytest itself is reset to the default in every child."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


@pytest.fixture(params=list(envs.ENV_IDS))
def env_id(request) -> str:
    return request.param


@pytest.fixture
def make_env():
    """Make envs through gymnasium and close them after the test."""
    made = []

    def _make(env_id: str, **kwargs) -> gym.Env:
        env = gym.make(env_id, **kwargs)
        made.append(env)
        return env

    yield _make
    for env in made:
        env.close()


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """SQLAlchemy URL of a database on a throw-away PostgreSQL server, stopped and deleted after the test.

    Skips when the server or driver package is missing: tests using it are marked slow and run outside CI.
    """
    try:
        postgres.site_dir()
    except postgres.PostgresUnavailable as error:
        pytest.skip(str(error))
    with postgres.postgres_server() as url:
        yield url
