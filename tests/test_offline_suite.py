"""``benchmarks/offline_suite.py``, the suite the constructors' defaults are chosen on: a tiny run of it writes one
record a run scored against its own data, resumes by run, and refuses a bad variant on one line."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch as th

SUITE = Path(__file__).parents[1] / "benchmarks" / "offline_suite.py"
TINY = ["--datasets", "mountaincar-weak", "--algorithms", "bc", "iql", "--steps", "5", "--eval-episodes", "1", "--seeds", "0"]


def suite(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SUITE), *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("suite")
    finished = suite(str(out), *TINY)
    assert finished.returncode == 0, finished.stderr[-3000:]
    return out


def test_each_run_is_one_record_scored_against_its_own_data(out):
    data = np.load(out / "data" / "mountaincar-weak.npz")
    episodes = int(data["terminations"].sum() + (data["truncations"] & ~data["terminations"]).sum())
    success = float(data["terminations"].sum()) / episodes
    runs = sorted(path.name for path in (out / "runs").iterdir())
    assert runs == ["mountaincar-weak-sb3-cql-bc-seed0.json", "mountaincar-weak-sb3-cql-iql-seed0.json"]
    for name, algorithm in zip(runs, ("bc", "iql"), strict=True):
        record = json.loads((out / "runs" / name).read_text())
        assert (record["dataset"], record["library"], record["algorithm"], record["label"]) == (
            "mountaincar-weak", "sb3-cql", algorithm, None)  # fmt: skip
        assert (record["seed"], record["steps"], record["keywords"]) == (0, 5, {})
        assert record["data"] == pytest.approx(success) and episodes == 100
        assert len(record["successes"]) == len(record["returns"]) == 1
        assert record["score"] == pytest.approx(np.mean(record["successes"]))  # a sparse task: scored by success
    umask = os.umask(0)
    os.umask(umask)
    assert {(out / "runs" / name).stat().st_mode & 0o777 for name in runs} == {0o666 & ~umask}  # as any file written


def test_each_model_is_kept_beside_its_record_and_loads_with_its_class(out):
    from sb3_cql import BC, IQL

    assert sorted(path.name for path in (out / "models").iterdir()) == [
        "mountaincar-weak-sb3-cql-bc-seed0.zip", "mountaincar-weak-sb3-cql-iql-seed0.zip"]  # fmt: skip
    model = IQL.load(out / "models" / "mountaincar-weak-sb3-cql-iql-seed0.zip")
    assert isinstance(model, IQL) and model.num_timesteps == 5
    assert isinstance(BC.load(out / "models" / "mountaincar-weak-sb3-cql-bc-seed0.zip"), BC)


def test_the_same_command_skips_the_runs_already_made(out):
    before = {path.name: path.stat().st_mtime_ns for path in (out / "runs").iterdir()}
    finished = suite(str(out), *TINY)
    assert finished.returncode == 0, finished.stderr[-3000:]
    assert "seed0:" not in finished.stdout  # no run made again
    assert {path.name: path.stat().st_mtime_ns for path in (out / "runs").iterdir()} == before
    table = suite(str(out), "--table").stdout
    assert "| our BC | 0." in table and "| our IQL |" in table and "| the data | 0.46 |" in table


@pytest.mark.parametrize("variant", ["raw", "raw={normalize_observations: false}", 'raw=["normalize_observations"]',
                                     'raw={"normalise_observations": false}'])  # fmt: skip
def test_a_bad_variant_is_refused_on_one_line(tmp_path, variant):
    finished = suite(str(tmp_path), *TINY, "--variant", variant)
    assert finished.returncode == 2
    assert [line for line in finished.stderr.splitlines() if line.startswith("offline_suite.py: error:")]
    assert "Traceback" not in finished.stderr and not (tmp_path / "runs").exists()
    if "normalise" in variant:
        assert "did you mean normalize_observations?" in finished.stderr


def test_the_minari_source_trains_ours_on_the_same_data_as_the_buffer(out):
    """``--source minari`` writes each data set as a Minari dataset under OUT/minari and gives it to ours as
    ``dataset=``: the same arrays, so the same trained parameters as from the buffer, in rows labelled ``minari``."""
    from sb3_cql import BC, IQL

    finished = suite(str(out), *TINY, "--source", "minari")
    assert finished.returncode == 0, finished.stderr[-3000:]
    assert (out / "minari" / "offline-suite" / "mountaincar-weak-v0").is_dir()
    for algorithm, model_class in (("bc", BC), ("iql", IQL)):
        record = json.loads((out / "runs" / f"mountaincar-weak-sb3-cql-{algorithm}-minari-seed0.json").read_text())
        assert (record["label"], record["source"]) == ("minari", "minari")
        from_minari = model_class.load(out / "models" / f"mountaincar-weak-sb3-cql-{algorithm}-minari-seed0.zip")
        from_buffer = model_class.load(out / "models" / f"mountaincar-weak-sb3-cql-{algorithm}-seed0.zip")
        minari_state, buffer_state = from_minari.policy.state_dict(), from_buffer.policy.state_dict()
        assert minari_state.keys() == buffer_state.keys()
        assert all(th.equal(minari_state[key], buffer_state[key]) for key in minari_state)


def test_a_task_whose_simulator_is_missing_is_refused_on_one_line_before_any_run(tmp_path):
    shadow = tmp_path / "shadow" / "Box2D"  # Box2D as an interpreter without it meets it: its import fails
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text("raise ImportError('No module named Box2D')\n")
    finished = subprocess.run([sys.executable, str(SUITE), str(tmp_path / "out"), "--datasets", "lunar-noisy",
                               "--algorithms", "bc", "--steps", "5", "--eval-episodes", "1", "--seeds", "0"],
                              capture_output=True, text=True, timeout=600,
                              env={**os.environ, "PYTHONPATH": str(shadow.parent)})  # fmt: skip
    assert finished.returncode == 2
    errors = [line for line in finished.stderr.splitlines() if line.startswith("offline_suite.py: error:")]
    assert len(errors) == 1 and "LunarLanderContinuous-v3" in errors[0] and "box2d" in errors[0].lower()
    assert "Traceback" not in finished.stderr and not (tmp_path / "out" / "data").exists()


def interpreter_with(tmp_path: Path, d3rlpy_source: str) -> str:
    """This interpreter with a ``d3rlpy`` package of ``d3rlpy_source`` in front of any installed one."""
    shadow = tmp_path / "shadow" / "d3rlpy"
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text(d3rlpy_source)
    wrapper = tmp_path / "python"
    wrapper.write_text(f'#!/bin/sh\nPYTHONPATH="{shadow.parent}" exec "{sys.executable}" "$@"\n')
    wrapper.chmod(0o755)
    return str(wrapper)


@pytest.mark.parametrize("case", ["no interpreter", "no d3rlpy"])
def test_a_d3rlpy_interpreter_that_cannot_run_it_is_refused_on_one_line_before_any_run(tmp_path, case):
    python = str(tmp_path / "none" / "python")
    if case == "no d3rlpy":
        python = interpreter_with(tmp_path, "raise ImportError('No module named d3rlpy')\n")
    finished = suite(str(tmp_path / "out"), *TINY, "--d3rlpy-python", python)
    assert finished.returncode == 2
    errors = [line for line in finished.stderr.splitlines() if line.startswith("offline_suite.py: error:")]
    assert len(errors) == 1 and "--d3rlpy-python" in errors[0] and "d3rlpy==2.8.1" in errors[0]
    assert "Traceback" not in finished.stderr and not (tmp_path / "out" / "runs").exists()


def test_a_d3rlpy_run_that_fails_ends_on_one_line_with_its_log_kept_and_no_record(tmp_path):
    python = interpreter_with(tmp_path, "")  # imports, and has none of d3rlpy's algorithms
    out = tmp_path / "out"
    finished = suite(str(out), *TINY, "--libraries", "d3rlpy", "--d3rlpy-python", python)
    assert finished.returncode == 1
    errors = [line for line in finished.stderr.splitlines() if line.startswith("offline_suite.py: error:")]
    assert len(errors) == 1 and "d3rlpy's bc on mountaincar-weak, seed 0, failed" in errors[0]
    assert "Traceback" not in finished.stderr and not (out / "runs").exists()
    log = out / "logs" / "mountaincar-weak-d3rlpy-bc-seed0.log"
    assert "Traceback" in log.read_text() and str(log) in errors[0]


def test_the_per_seed_table_gives_each_seed_its_place_and_a_dash_where_a_row_lacks_it(out, tmp_path):
    (tmp_path / "runs").mkdir()
    for path in (out / "runs").glob("*.json"):
        (tmp_path / "runs" / path.name).write_text(path.read_text())
    record = json.loads((out / "runs" / "mountaincar-weak-sb3-cql-iql-seed0.json").read_text())
    (tmp_path / "runs" / "mountaincar-weak-sb3-cql-iql-seed1.json").write_text(json.dumps({**record, "seed": 1}))
    rows = {line.split(" | ")[0]: line for line in suite(str(tmp_path), "--table", "--per-seed").stdout.splitlines()}
    iql = record["score"]
    assert rows["| our IQL"] == f"| our IQL | {iql:.2f} / {iql:.2f} |"
    assert rows["| our BC"].endswith(" / - |")
    assert suite(str(tmp_path), "--per-seed").returncode == 2
