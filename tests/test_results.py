"""The models committed under results/models: each loads with ``CQL.load`` and acts in the task it was fine-tuned on,
and it is the model at the end of the fine-tuning its record describes."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import CQL

RESULTS = Path(__file__).resolve().parents[1] / "results"
FINETUNED = sorted((RESULTS / "models").glob("finetune-*.zip"))
MAX_BYTES = 20 * 1024 * 1024  # what the repository holds of models at most


def test_the_committed_models_fit_in_the_repository():
    assert FINETUNED and sum(path.stat().st_size for path in FINETUNED) <= MAX_BYTES


@pytest.mark.parametrize("path", FINETUNED, ids=lambda path: path.stem)
def test_a_committed_fine_tuned_model_loads_and_acts_in_its_task(path):
    name, seed = path.stem.rsplit("-", 1)  # finetune-<task>-seed<N>
    task = name.removeprefix("finetune-")
    record = json.loads((RESULTS / f"finetune-{task}" / "records" / "train" / f"cql-finetune-{task}-{seed}.json").read_text())
    model = CQL.load(path)
    assert model.num_timesteps == record["training_steps"] and model.cql_calibrated
    env = gym.make(task, **record["env_kwargs"])
    observation, _ = env.reset(seed=0)
    action, _ = model.predict(observation, deterministic=True)
    assert env.action_space.contains(action.astype(env.action_space.dtype))
    np.testing.assert_array_equal(model.predict(observation, deterministic=True)[0], action)
    env.close()
