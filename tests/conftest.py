from collections.abc import Iterator

import gymnasium as gym
import postgres
import pytest

import envs


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
