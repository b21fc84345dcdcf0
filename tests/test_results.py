"""The models committed under results/models: each loads with its class and acts in the task it was trained on, and
it is the model at the end of the training its record describes (the protocol's fine-tuning stage's in results/, a
study's in research/studies/, read as data); the fine-tuning stage's folder says how it was made."""

import json
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

import envs  # noqa: F401  (registers the tasks)
from sb3_cql import IQL, CalQL

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
STUDIES_DIR = ROOT / "research" / "studies"
FINETUNED = sorted((RESULTS / "models").glob("finetune-*.zip"))
OFFLINE_YAW = sorted((RESULTS / "models").glob("offline-yaw-*.zip"))
MAX_BYTES = 24 * 1024 * 1024  # what the repository holds of models at most


def test_the_committed_models_fit_in_the_repository():
    models = sorted((RESULTS / "models").glob("*.zip"))
    assert models == sorted(FINETUNED + OFFLINE_YAW)  # every committed model is checked below
    assert sum(path.stat().st_size for path in models) <= MAX_BYTES


#: The study of the zoo's fine-tuning runs from the random-yaw IQL model, a folder ``short-seed<N>`` a seed.
FINETUNE_IQL = STUDIES_DIR / "finetune-iql"


def record_of(path: Path) -> tuple[str, type, dict]:
    """The task, class and record of a committed model: ``finetune-<task>-seed<N>.zip`` is the protocol's fine-tuning
    stage (Cal-QL; its record in ``results/finetune-<task>/records``), ``finetune-iql-<task>-seed<N>.zip`` the zoo's
    fine-tuning of the random-yaw IQL model (its record in ``research/studies/finetune-iql/short-seed<N>``)."""
    name, seed = path.stem.rsplit("-", 1)
    task = name.removeprefix("finetune-")
    if task.startswith("iql-"):
        return task.removeprefix("iql-"), IQL, json.loads((FINETUNE_IQL / f"short-{seed}" / "record.json").read_text())
    record = RESULTS / f"finetune-{task}" / "records" / "train" / f"cql-finetune-{task}-{seed}.json"
    return task, CalQL, json.loads(record.read_text())


@pytest.mark.parametrize("path", FINETUNED, ids=lambda path: path.stem)
def test_a_committed_fine_tuned_model_loads_and_acts_in_its_task(path):
    task, algorithm, record = record_of(path)
    model = algorithm.load(path)
    assert type(model) is algorithm and model.num_timesteps == record["training_steps"]
    env = gym.make(task, **record["env_kwargs"])
    observation, _ = env.reset(seed=0)
    action, _ = model.predict(observation, deterministic=True)
    assert env.action_space.contains(action.astype(env.action_space.dtype))
    np.testing.assert_array_equal(model.predict(observation, deterministic=True)[0], action)
    env.close()


def test_the_committed_iql_fine_tuned_model_was_trained_by_its_zoo_configuration():
    """Every fine-tuning keyword of the shipped configuration is the model's, its evaluation record beside it covers
    100 episodes of each task, and it started from the committed random-yaw model."""
    path = RESULTS / "models" / "finetune-iql-PandaForce-v0-seed1.zip"
    task, _, record = record_of(path)
    config = yaml.safe_load((ROOT / record["conf_file"]).read_text())[task]
    model = IQL.load(path)
    for key in ("online_fraction", "online_buffer_size", "learning_starts", "train_freq", "gradient_steps",
                "deterministic_rollouts"):  # fmt: skip
        value = model.train_freq.frequency if key == "train_freq" else getattr(model, key)
        assert value == config[key], key
    assert record["env_kwargs"] == config["env_kwargs"]
    assert (ROOT / record["started_from"]).is_file() and f"-i {record['started_from']}" in record["command"]
    assert f"-n {record['training_steps']}" in record["command"] and f"--seed {record['seed']}" in record["command"]
    evaluation = json.loads((FINETUNE_IQL / f"short-seed{record['seed']}" / "final-eval.json").read_text())
    assert {name: len(task_record["episodes"]) for name, task_record in evaluation["tasks"].items()} == {
        "PandaForce-v0": 100, "Panda-v0": 100, "PandaPerturbed-v0": 100,
    }  # fmt: skip


#: The row of ``research/studies/offline-yaw`` whose final model an ``offline-yaw-<task>-<algo>-seed<N>.zip`` is, its
#: class, the zoo configuration in ``hyperparams/`` that trains it, and the keywords the row sets otherwise (the
#: zoo's ``--hyperparams``): the committed model was trained before the configuration lowered the TD targets to 1.
OFFLINE_ROWS = {"iql": ("iql-yaw-ddpgawr4-40k-mfa", IQL, "iql_yaw.yml", {"target_ceiling": None})}
#: Keys of a zoo configuration that are not the algorithm's attributes of the same name.
ZOO_ONLY_KEYS = {
    "policy",
    "dataset",
    "env_kwargs",
    "n_timesteps",
    "policy_kwargs",
    "monitor_kwargs",
    "eval_freq",
    "n_eval_episodes",
}


@pytest.mark.parametrize("path", OFFLINE_YAW, ids=lambda path: path.stem)
def test_a_committed_offline_model_loads_with_its_class_and_acts_in_its_task(path):
    """The final model of its row's training, with the row's evaluation record beside it, trained as its zoo
    configuration says (its steps and every keyword of the algorithm), and acting with its own action (``best_of_n``
    1) in the delta actions it was trained in."""
    task, algo, seed = re.fullmatch(r"offline-yaw-(.+)-([a-z]+)-seed(\d+)", path.stem).groups()
    row, algorithm, config_file, overrides = OFFLINE_ROWS[algo]
    record = json.loads((STUDIES_DIR / "offline-yaw" / f"{row}-seed{seed}.json").read_text())
    assert record["algo"] == algo and all(len(record["tasks"][name]["episodes"]) == 100 for name in record["tasks"])
    shipped = yaml.safe_load((ROOT / "hyperparams" / config_file).read_text())[task]
    assert overrides.keys() <= shipped.keys()  # each override names a keyword the configuration sets
    config = {**shipped, **overrides}
    model = algorithm.load(path)
    assert model.num_timesteps == config["n_timesteps"] and model.best_of_n == 1
    for key in config.keys() - ZOO_ONLY_KEYS:
        value = getattr(model, key)
        assert (value(1.0) if callable(value) else value) == config[key], key  # a rate is saved as SB3's schedule
    env = gym.make(task, **config["env_kwargs"])
    assert config["env_kwargs"]["action_mode"] == record["tasks"][task]["action_mode"]
    observation, _ = env.reset(seed=0)
    action, _ = model.predict(observation, deterministic=True)
    assert env.action_space.contains(action.astype(env.action_space.dtype))
    np.testing.assert_array_equal(model.predict(observation, deterministic=True)[0], action)
    env.close()


#: The protocol's own folders at the top of results/: every other folder there is the protocol's fine-tuning stage (the
#: studies are in research/studies/, their README check in research/tests/).
PROTOCOL_FOLDERS = {"figures", "records", "runs", "models"}
FINETUNE_STAGES = sorted(path for path in RESULTS.iterdir() if path.is_dir() and path.name not in PROTOCOL_FOLDERS)


def test_results_holds_the_protocol_and_its_fine_tuning_stage_only():
    assert [path.name for path in FINETUNE_STAGES] == ["finetune-PandaForce-v0"]


@pytest.mark.parametrize("folder", FINETUNE_STAGES, ids=lambda path: path.name)
def test_the_fine_tuning_stage_names_its_command_and_date(folder):
    readme = (folder / "README.md").read_text()
    assert "python -m sb3_cql.protocol " in readme and re.search(r"\b2026-\d\d-\d\d\b", readme)
    assert f"]({folder.name}/README.md)" in (RESULTS / "README.md").read_text()  # listed in the results folder's index
