"""The models committed under ``results/models`` load with their class and act as they did when they were committed:
the same deterministic actions on a fixed set of PandaForce-v0 observations (``tests/data/model_actions.npz``, recorded
from the models with the code they were trained with). The random-yaw IQL model is the starting point of fine-tuning:
a change to the policies, the normaliser or ``load`` that changed its actions would break it silently."""

from pathlib import Path

import numpy as np
import pytest

from sb3_cql import IQL, CalQL

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = np.load(ROOT / "tests" / "data" / "model_actions.npz")
MODELS = {
    "finetune-PandaForce-v0-seed1": CalQL,
    "finetune-iql-PandaForce-v0-seed1": IQL,
    "offline-yaw-PandaForce-v0-iql-seed1": IQL,
}


def test_every_committed_model_has_reference_actions():
    assert sorted(path.stem for path in (ROOT / "results" / "models").glob("*.zip")) == sorted(MODELS)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_committed_model_loads_with_its_class_and_acts_as_committed(name):
    model = MODELS[name].load(ROOT / "results" / "models" / f"{name}.zip", device="cpu")
    assert type(model) is MODELS[name]
    actions, _ = model.predict(REFERENCE["observations"], deterministic=True)
    np.testing.assert_allclose(actions, REFERENCE[name], rtol=0, atol=1e-5)
