"""The protocol command, ``python -m sb3_cql.protocol``, end to end with the real zoo on a 4-episode dataset."""

import contextlib
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rollouts import TINY_PANDA_COLLECT
from startup import interrupt_while_starting

from sb3_cql.protocol.runs import Run, model_timesteps

TASKS = ["Panda-v0", "PandaForce-v0", "PandaPerturbed-v0"]
# Tiny networks and batches, short runs, one episode per evaluation: the point is the plumbing.
TINY = ["--zoo-args", "--hyperparams batch_size:64 policy_kwargs:dict(net_arch=[32,32])", "--seeds", "117",
        "--eval-episodes", "1", "--episodes", "1"]  # fmt: skip


class Bench:
    """A working folder whose datasets folder holds a 4-episode ``sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0``, our configs'."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.env = {**os.environ, "MINARI_DATASETS_PATH": str(root / "datasets"), "MPLBACKEND": "Agg"}

    def command(self, *args: str, module: str = "sb3_cql.protocol") -> list[str]:
        return [sys.executable, "-m", module, *args]

    def run(self, *args: str, module: str = "sb3_cql.protocol", check: bool = True) -> subprocess.CompletedProcess:
        result = subprocess.run(self.command(*args, module=module), cwd=self.root, env=self.env, capture_output=True,
                                text=True, timeout=900)  # fmt: skip
        if check:
            assert result.returncode == 0, f"{args} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
        return result


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Bench:
    bench = Bench(tmp_path_factory.mktemp("bench"))
    bench.run(*TINY_PANDA_COLLECT, module="sb3_cql.data")
    return bench


@pytest.fixture(scope="module")
def quick(bench) -> tuple[Path, str]:
    """CQL, BC, SAC and the PD controllers through the whole protocol: 200 steps, evaluated and saved every 100."""
    args = ["--algos", "cql", "bc", "sac", "pid", "pid-regrasp", "--n-timesteps", "200", "--eval-freq", "100",
            "--save-freq", "100", "--results-dir", "quick", *TINY]  # fmt: skip
    output = bench.run(*args).stdout
    return bench.root / "quick", output


def test_protocol_records_every_unit_and_makes_the_table_and_figures(quick):
    results, output = quick
    assert "[train cql seed 117] done: 200 steps in 1 segment(s)" in output
    # One worker: a finished training's evaluations run before the trainings still waiting.
    assert output.index("[eval cql seed 117 PandaPerturbed-v0] success rate") < output.index("[train bc seed 117] started")
    report = json.loads((results / "results.json").read_text())
    rows = {(r["algo"], r["seed"], r["task"]) for r in report["evaluations"]}
    assert rows == {(algo, 117, task) for algo in ("cql", "bc", "sac", "pid", "pid-regrasp") for task in TASKS}
    for record in report["evaluations"]:
        assert record["episodes"] == 1 and 0.0 <= record["success_rate"] <= 1.0
        if record["algo"] not in ("pid", "pid-regrasp"):
            assert record["training_steps"] == 200 and record["best_step"] in (100, 200)
    assert report["summary"]["pid"]["Panda-v0"]["mean"] == 1.0
    assert report["summary"]["pid-regrasp"]["Panda-v0"]["mean"] == 1.0
    assert set(report["summary"]["cql"]["Panda-v0"]) >= {"mean", "std", "iqm", "iqm_ci95", "seeds"}
    assert report["settings"]["n_timesteps"] == 200
    system = report["system"]
    assert system["cpu_count"] and system["versions"]["torch"] and system["versions"]["stable-baselines3"]
    training = {r["algo"]: r for r in report["training"]}
    assert training["cql"]["best_model"].startswith("runs/seed117/cql/Panda-v0_1/")
    assert training["cql"]["train_wall_time_s"] > 0

    csv_lines = (results / "results.csv").read_text().splitlines()
    assert csv_lines[0].startswith("algo,seed,task,success_rate,episodes,best_step,training_steps")
    assert len(csv_lines) == 1 + 15
    table = (results / "table.md").read_text()
    for row in ("| CQL |", "| BC |", "| PID |", "| PID-REGRASP |", "| SAC |"):
        assert table.count(row) == 2  # mean ± std, and IQM [CI]
    assert table.index("| CQL |") < table.index("| PID |") < table.index("| SAC |")  # the thesis's order
    assert training["bc"]["env_kwargs"] == {"action_mode": "delta"} and training["bc"]["training_steps"] == 200
    figures = {path.name for path in (results / "figures").glob("*.png")}
    assert figures == {"training_success.png", "training_losses.png", "final_success.png"} | {
        f"filmstrip_{task}.png" for task in TASKS
    }


def test_the_yaw_controllers_are_scripted_rows_in_the_tables_order(tmp_path):
    bench = Bench(tmp_path)
    bench.run("--algos", "pid-regrasp-aligned", "pid-regrasp-yaw", "--tasks", "Panda-v0", "--seeds", "117", "--episodes",
              "1", "--results-dir", "scripted")  # fmt: skip
    report = json.loads((tmp_path / "scripted" / "results.json").read_text())
    assert report["training"] == []  # evaluated, never trained
    assert {row: report["summary"][row]["Panda-v0"]["mean"] for row in report["summary"]} == {
        "pid-regrasp-yaw": 1.0, "pid-regrasp-aligned": 1.0
    }  # fmt: skip
    table = (tmp_path / "scripted" / "table.md").read_text()
    assert table.index("| PID-REGRASP-YAW |") < table.index("| PID-REGRASP-ALIGNED |")
    assert (tmp_path / "scripted" / "figures" / "filmstrip_Panda-v0.png").is_file()


def test_a_second_run_does_no_work_and_report_only_remakes_the_outputs(bench, quick):
    results, _ = quick
    args = ["--algos", "cql", "bc", "sac", "pid", "--n-timesteps", "200", "--eval-freq", "100", "--save-freq", "100",
            "--results-dir", "quick", "--no-filmstrips", *TINY]  # fmt: skip
    output = bench.run(*args).stdout
    assert "queued" not in output and "started" not in output and "units: 0 done, 15 already recorded" in output
    assert sorted(path.name for path in (results / "runs" / "seed117" / "cql").glob("Panda-v0_*")) == ["Panda-v0_1"]

    (results / "table.md").unlink()
    bench.run("--report-only", "--results-dir", "quick", "--no-filmstrips")
    assert "| CQL |" in (results / "table.md").read_text()


def test_report_only_leaves_out_of_the_filmstrips_a_model_not_on_disk(bench, quick):
    results, _ = quick
    copy = bench.root / "without-sac-model"
    shutil.copytree(results, copy)
    record = json.loads((copy / "records" / "train" / "sac-seed117.json").read_text())
    (copy / record["best_model"]).unlink()  # as in a clone: models are not committed with the records
    started = time.time()
    output = bench.run("--report-only", "--results-dir", "without-sac-model").stdout
    assert f"filmstrips: sac left out, its model {copy / record['best_model']} is not on disk" in output
    for task in TASKS:  # made again, with the other policies
        assert (copy / "figures" / f"filmstrip_{task}.png").stat().st_mtime >= started - 1


def test_clear_errors(bench, quick):
    def one_line_error(*args: str) -> str:
        result = bench.run(*args, check=False)
        assert result.returncode == 2 and "Traceback" not in result.stderr
        (line,) = result.stderr.strip().splitlines()
        assert line.startswith("python -m sb3_cql.protocol: error: ")
        return line

    assert "unknown algo 'nothing'" in one_line_error("--algos", "cql", "nothing", "--results-dir", "errors")
    assert "other settings" in one_line_error("--algos", "pid", "--results-dir", "quick", "--episodes", "3")
    assert "no protocol results" in one_line_error("--report-only", "--results-dir", "nowhere")
    missing = one_line_error("--algos", "bc", "--results-dir", "errors", "--zoo-args",
                             "--hyperparams dataset:\"'sb3cql/Panda-v0/nothing-here-v0'\"")  # fmt: skip
    assert "dataset sb3cql/Panda-v0/nothing-here-v0 not found" in missing
    missing = one_line_error("--algos", "cql", "--results-dir", "errors", "--dataset", "sb3cql/Panda-v0/nothing-here-v0")
    assert "dataset sb3cql/Panda-v0/nothing-here-v0 not found" in missing
    assert "none of --algos bc pid fine-tunes online (cql does)" in one_line_error(
        "--algos", "bc", "pid", "--finetune", "PandaForce-v0", "--results-dir", "errors")  # fmt: skip
    assert not (bench.root / "errors" / "runs").exists()  # refused before any work


def test_dataset_option_sets_the_offline_algorithms_dataset_only(tmp_path):
    from sb3_cql.protocol.records import ResultsFolder, write_json
    from sb3_cql.protocol.runner import ProtocolError, Settings

    thesis = "sb3cql/Panda-v0/noisy-regrasp-delta-v0"
    settings = Settings(zoo_args=["--hyperparams", "batch_size:64", "--verbose", "0"], dataset=thesis)
    assert settings.dataset_args(None) == settings.zoo_args  # an online algorithm's config has no dataset
    args = settings.dataset_args("sb3cql/Panda-v0/noisy-regrasp-delta-1k-v0")
    assert args == ["--hyperparams", f"dataset:'{thesis}'", "batch_size:64", "--verbose", "0"]  # one --hyperparams
    assert Settings(dataset=thesis).dataset_args("x") == ["--hyperparams", f"dataset:'{thesis}'"]
    assert Settings(zoo_args=["-n", "5"]).dataset_args("x") == ["-n", "5"]
    # A results folder recorded before the option existed keeps working with its default, and refuses another dataset.
    results = ResultsFolder(tmp_path)
    write_json(results.protocol, {"settings": {"n_timesteps": None, "eval_freq": None, "eval_episodes": None,
                                               "episodes": 100, "zoo_args": []}, "train_env": "Panda-v0"})  # fmt: skip
    Settings().check_folder(results)
    with pytest.raises(ProtocolError, match="other settings"):
        Settings(dataset=thesis).check_folder(results)


def test_a_failing_zoo_run_shows_its_log(bench):
    result = bench.run("--algos", "cql", "--tasks", "Panda-v0", "--n-timesteps", "10", "--results-dir", "failing run",
                       "--zoo-args", "--hyperparams no_such_argument:1", "--no-filmstrips", check=False)  # fmt: skip
    assert result.returncode != 0
    assert "[train cql seed 117] FAILED" in result.stdout
    assert "the zoo failed (exit 2)" in result.stderr  # an unknown hyperparameter: the zoo's one line, in the log's tail
    assert "python -m rl_zoo3.train: error: CQL got unexpected keyword arguments: no_such_argument" in result.stderr
    # The log names the zoo command quoted for the shell: a results folder with a space is one word.
    (logged,) = re.findall(r"^=== .* segment Panda-v0_1: (.+)$", (bench.root / "failing run" / "runs" / "seed117" /
                                                                  "cql.log").read_text(), re.MULTILINE)  # fmt: skip
    command = shlex.split(logged)
    assert command[command.index("-f") + 1] == str(bench.root / "failing run" / "runs" / "seed117")


def test_a_killed_training_resumes_from_its_checkpoint(bench):
    args = ["--algos", "cql", "--tasks", "Panda-v0", "--n-timesteps", "300", "--eval-freq", "100", "--save-freq", "100",
            "--results-dir", "killed", "--no-filmstrips", *TINY]  # fmt: skip
    first = bench.root / "killed" / "runs" / "seed117" / "cql" / "Panda-v0_1"
    process = subprocess.Popen(bench.command(*args), cwd=bench.root, env=bench.env, start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 600
        # Complete: a checkpoint appears whole (written beside its name, then renamed), and the wait reads it back.
        while model_timesteps(first / "rl_model_100_steps.zip") is None:
            assert process.poll() is None and time.monotonic() < deadline, "no checkpoint before the end"
            time.sleep(0.2)
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # the runner, its worker and the zoo, mid-training
        process.wait()
    assert not (bench.root / "killed" / "records" / "train").exists()

    output = bench.run(*args).stdout
    assert "[train cql seed 117] done: 300 steps in 2 segment(s)" in output
    record = json.loads((bench.root / "killed" / "records" / "train" / "cql-seed117.json").read_text())
    resumed = record["segments"][1]
    assert resumed["folder"] == "Panda-v0_2" and resumed["resumed_from"].startswith("Panda-v0_1/rl_model_")
    assert resumed["offset"] in (100, 200)
    run = Run.read(bench.root / "killed" / "runs" / "seed117" / "cql", "Panda-v0")
    steps, rates = run.evaluations()
    # Each step at most once (what the killed segment did after its checkpoint is dropped), the resumed segment's
    # evaluations all there; the one a kill interrupted right after its checkpoint is not redone.
    assert steps.tolist() == sorted(set(steps.tolist())) and set(steps.tolist()) <= {100, 200, 300}
    assert {step for step in (100, 200, 300) if step > resumed["offset"]} <= set(steps.tolist())
    best_step, best_rate, best_path = run.best_model()
    assert best_rate == rates.max() and best_step == steps[rates.argmax()] and record["best_step"] == best_step
    assert run.scalars("train/actor_loss")[0].max() <= 300


def _zoo_runs(marker: str) -> list[int]:
    """Process ids of the live ``rl_zoo3.train`` processes whose command line holds ``marker``."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            command = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode() if proc.name.isdigit() else ""
        except OSError:  # gone meanwhile
            continue
        if "rl_zoo3.train" in command and marker in command:
            pids.append(int(proc.name))
    return pids


def test_a_killed_runner_takes_its_workers_and_zoo_runs_along(bench):
    args = ["--algos", "cql", "--tasks", "Panda-v0", "--n-timesteps", "100000", "--results-dir", "orphans",
            "--no-filmstrips", *TINY]  # fmt: skip
    marker = str(bench.root / "orphans")
    process = subprocess.Popen(bench.command(*args), cwd=bench.root, env=bench.env, start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 600
        while not _zoo_runs(marker):
            assert process.poll() is None and time.monotonic() < deadline, "the training never started"
            time.sleep(0.2)
        process.kill()  # the runner alone, with no chance to clean up (its worker and the zoo are not signalled)
        process.wait()
        deadline = time.monotonic() + 120
        while _zoo_runs(marker):
            assert time.monotonic() < deadline, "the zoo run outlived its runner"
            time.sleep(0.2)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)


def test_an_algorithms_confidence_interval_depends_on_its_own_scores_alone():
    """Not on the other rows, nor on numpy's global generator, which rliable's bootstrap draws from."""
    import numpy as np

    from sb3_cql.protocol.report import summarise

    tasks = ["Panda-v0", "PandaForce-v0"]
    cql = ([1, 2, 3, 4, 5], np.array([[1.0, 0.2], [0.9, 0.3], [0.95, 0.1], [0.8, 0.25], [1.0, 0.15]]))
    np.random.seed(1)
    alone = summarise({"cql": cql}, tasks)
    assert np.random.randint(1000) == np.random.RandomState(1).randint(1000)  # the global generator is left as found
    np.random.seed(2)  # (rliable resamples with numpy's global generator)
    with_others = summarise({"cql": cql, "sac": ([1, 2, 3], np.zeros((3, 2))), "bc": cql}, tasks)
    assert with_others["cql"] == alone["cql"] == with_others["bc"]
    low, high = alone["cql"]["Panda-v0"]["iqm_ci95"]
    assert low < alone["cql"]["Panda-v0"]["iqm"] < high


def test_a_checkpoint_cut_short_by_a_kill_is_not_resumed(tmp_path):
    """A truncated checkpoint (a copy cut short, or one SB3 wrote in place outside the zoo's runs and a kill cut
    short) must count as absent."""
    import yaml
    from stable_baselines3 import SAC

    segment = tmp_path / "cql" / "Pendulum-v1_1"
    (segment / "Pendulum-v1").mkdir(parents=True)
    (segment / "Pendulum-v1" / "args.yml").write_text(yaml.safe_dump({"n_timesteps": 300, "trained_agent": ""}))
    (segment / "Pendulum-v1" / "config.yml").write_text(yaml.safe_dump({"n_timesteps": 300}))
    model = SAC("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [8]}, buffer_size=10, device="cpu")
    for step in (100, 200):
        model.num_timesteps = step
        model.save(segment / f"rl_model_{step}_steps.zip")
    run = Run.read(tmp_path / "cql", "Pendulum-v1")
    assert run.latest_model() == (200, segment / "rl_model_200_steps.zip")

    whole = (segment / "rl_model_200_steps.zip").read_bytes()
    (segment / "rl_model_200_steps.zip").write_bytes(whole[: len(whole) // 2])
    assert model_timesteps(segment / "rl_model_200_steps.zip") is None
    assert run.latest_model() == (100, segment / "rl_model_100_steps.zip") and not run.is_complete()


def test_a_run_started_from_an_outside_model_begins_at_step_0_and_resumes_from_its_own(tmp_path):
    """A fine-tuning run's first segment continues (``-i``) a model from elsewhere: its steps start at 0; a later
    segment continues one of the run's own checkpoints."""
    import yaml
    from stable_baselines3 import SAC

    model = SAC("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [8]}, buffer_size=10, device="cpu")
    for number, source, steps in ((1, "/elsewhere/Panda-v0_1/best_model.zip", (100, 200)),
                                  (2, "Pendulum-v1_1/rl_model_100_steps.zip", (50,))):  # fmt: skip
        segment = tmp_path / "cql" / f"Pendulum-v1_{number}"
        (segment / "Pendulum-v1").mkdir(parents=True)
        args = {"n_timesteps": 300 if number == 1 else 200, "trained_agent": source}
        (segment / "Pendulum-v1" / "args.yml").write_text(yaml.safe_dump(args))
        (segment / "Pendulum-v1" / "config.yml").write_text(yaml.safe_dump({"n_timesteps": 40_000}))
        for step in steps:
            model.num_timesteps = step
            model.save(segment / f"rl_model_{step}_steps.zip")
    with pytest.raises(RuntimeError, match="not a model of this run"):
        Run.read(tmp_path / "cql", "Pendulum-v1")  # an offline run never starts from elsewhere
    run = Run.read(tmp_path / "cql", "Pendulum-v1", outside_start=True)
    assert [(s.offset, s.cut, s.resumed_from) for s in run.segments] == [
        (0, 100, None), (100, None, "Pendulum-v1_1/rl_model_100_steps.zip")]  # fmt: skip
    assert run.n_timesteps == 300 and run.latest_model() == (150, tmp_path / "cql" / "Pendulum-v1_2" / "rl_model_50_steps.zip")

    for model_file in (tmp_path / "cql").rglob("*.zip"):  # a clone of the results: records and logs, no models
        model_file.unlink()
    run = Run.read(tmp_path / "cql", "Pendulum-v1", outside_start=True)
    assert [(s.offset, s.cut) for s in run.segments] == [(0, 100), (100, None)]  # the checkpoint's step from its name
    assert run.latest_model() is None


def test_fine_tuning_is_a_stage_of_its_own_rows_after_the_offline_training(bench, quick):
    results, _ = quick
    args = ["--algos", "cql", "--finetune", "PandaForce-v0", "--n-timesteps", "200", "--eval-freq", "100",
            "--save-freq", "100", "--results-dir", "quick", "--no-filmstrips", *TINY]  # fmt: skip
    output = bench.run(*args).stdout
    assert "[train cql seed 117] skipped: recorded" in output
    assert "[finetune cql seed 117 PandaForce-v0] done: 200 steps in 1 segment(s)" in output
    record = json.loads((results / "records" / "train" / "cql-finetune-PandaForce-v0-seed117.json").read_text())
    offline = json.loads((results / "records" / "train" / "cql-seed117.json").read_text())
    assert record["started_from"] == offline["best_model"] and record["train_env"] == "PandaForce-v0"
    assert record["best_model"].startswith("runs/seed117/finetune/cql/PandaForce-v0_1/")
    assert list((results / record["best_model"]).parent.glob("rl_model_replay_buffer_*_steps.pkl"))
    report = json.loads((results / "results.json").read_text())
    assert {r["task"] for r in report["evaluations"] if r["algo"] == "cql-finetune-PandaForce-v0"} == set(TASKS)
    (run,) = report["finetuning"]
    start = json.loads((results / "records" / "eval" / "cql-seed117-PandaForce-v0.json").read_text())["success_rate"]
    assert run["start"] == start and run["lowest_early"] is None  # no evaluation in the first 20% of 200 steps
    table = (results / "table.md").read_text()
    assert "| CQL + online on PandaForce-v0 |" in table and "Fine-tuning runs" in table
    assert (results / "figures" / "finetune_PandaForce-v0.png").is_file()
    assert "units: 0 done" in bench.run(*args).stdout  # recorded: skipped the second time


def test_ctrl_c_while_the_command_starts_is_one_line(tmp_path):
    status, stderr = interrupt_while_starting(Bench(tmp_path).command("--algos", "pid", "--results-dir", "started"),
                                              cwd=tmp_path)  # fmt: skip
    assert status == 130
    assert stderr.splitlines() == ["python -m sb3_cql.protocol: interrupted while starting: nothing done"]
    assert not (tmp_path / "started").exists()


def test_ctrl_c_during_the_protocol_ends_it_at_once_on_one_line_keeping_the_units_recorded(tmp_path):
    bench = Bench(tmp_path)
    # 80 episodes: Panda-v0's take the controller about 10 s, PandaForce-v0's (700 steps each, the fallen cylinder
    # never grasped) about 35 s, the margin the signal has to arrive while the second evaluation is under way.
    args = ["--algos", "pid", "--seeds", "117", "--tasks", "Panda-v0", "PandaForce-v0", "--episodes", "80",
            "--results-dir", "interrupted", "--no-filmstrips"]  # fmt: skip
    process = subprocess.Popen(bench.command(*args), cwd=tmp_path, env=bench.env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip
    try:
        # The first evaluation is recorded; the second (in a worker process) is under way.
        assert any(line.startswith("[eval pid seed 117 Panda-v0] success rate") for line in iter(process.stdout.readline, ""))
        os.killpg(process.pid, signal.SIGINT)  # the runner and its worker, as a terminal's Ctrl-C
        _, stderr = process.communicate(timeout=120)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
    results = (tmp_path / "interrupted").resolve()
    assert process.returncode == 130 and "Traceback" not in stderr
    assert stderr.splitlines() == [
        f"interrupted: the units done are recorded in {results}; the same command continues with the others"
    ]
    assert [path.name for path in (results / "records" / "eval").iterdir()] == ["pid-seed117-Panda-v0.json"]
