import signal
from collections.abc import Iterator

import gymnasium as gym
import postgres
import pytest

import envs


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
