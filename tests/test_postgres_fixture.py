"""The postgres_url fixture serves one Optuna study to several processes."""

import subprocess
import sys

import optuna
import pytest

WORKER = """
import sys
import optuna

study = optuna.load_study(study_name=sys.argv[1], storage=sys.argv[2])
study.optimize(lambda trial: trial.suggest_float("x", 0.0, 1.0), n_trials=2)
"""


@pytest.mark.slow
def test_two_processes_share_a_postgres_study(postgres_url):
    study = optuna.create_study(storage=postgres_url, study_name="shared", direction="maximize")
    workers = [subprocess.Popen([sys.executable, "-c", WORKER, "shared", postgres_url]) for _ in range(2)]
    assert [worker.wait(timeout=120) for worker in workers] == [0, 0]
    trials = study.get_trials(deepcopy=False, states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 4
