import gymnasium as gym
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
