"""The research scripts in research/scripts/: each run end to end as a subprocess on a tiny dataset and clone, their
command lines, and the backup variants of cql_from_clone.py. Not part of the default suite:
``python -m pytest -n 0 research/tests``.

The seven script runs start together, once per module (each is mostly start-up time), and the tests check their
results.
"""

import ast
import importlib.util
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch as th
from rollouts import random_rollouts
from stable_baselines3 import SAC

import envs
from sb3_cql import BC, CQL, IQL, CalQL
from sb3_cql.common import SettingError
from sb3_cql.data import CollectionSpec, collect_dataset, load_dataset

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS_DIR = ROOT / "research" / "scripts"
SCRIPTS = ("acting_noise", "action_drift", "advantage_weights", "bc_continued", "closing_values", "cql_from_clone",
           "grasp_stalls", "gripper_reopenings", "q_probe", "values_vs_returns")  # fmt: skip
FINETUNED_STEPS = 700  # one Panda-v0 episode, cut by the time limit unless it succeeds
DATASET = "sb3cql/Panda-v0/tiny-regrasp-delta-v0"
YAW_DATASET = "sb3cql/PandaForce-v0/tiny-regrasp-yaw-delta-v0"
CHUNK = 2
TINY = {"batch_size": 16, "bc_steps": 1, "policy_kwargs": {"net_arch": [32]}}
ACTION_DIM = 9
FLOAT = r"-?\d+(?:\.\d+)?(?:e-?\d+)?"
SIGNED = r"[+-]\d+\.\d+"
FLOATS = rf"\[{FLOAT}(?:, {FLOAT}){{{ACTION_DIM - 1}}}\]"  # one value per action dimension


def load_script(name: str):
    """The script ``research/scripts/<name>.py`` as a module (its ``main`` is not run), importing ``_cli`` from its
    folder as the script run by path does."""
    if str(SCRIPTS_DIR) not in sys.path:
        sys.path.insert(0, str(SCRIPTS_DIR))
    spec = importlib.util.spec_from_file_location(f"research_scripts_{name}", SCRIPTS_DIR / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A 2-episode delta-action dataset of the regrasping PD controller (one success, one episode that reopens) in a
    temporary MINARI_DATASETS_PATH, a clone of it trained for a few steps, saved as ``bc.zip``, and a calibrated CQL
    model fine-tuned online for one episode, ``finetuned.zip`` with its online transitions ``finetuned_buffer.pkl``;
    and 2 PandaForce-v0 episodes of the noisy regrasping controller with random yaws, with a chunked CQL model trained
    a few steps on them, ``chunked.zip``, and an IQL model, ``iql.zip``."""
    root = tmp_path_factory.mktemp("research")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(root / "datasets"))
        spec = CollectionSpec(policy="noisy-regrasp", n_episodes=2, env_kwargs={"action_mode": "delta"})
        collect_dataset(spec, DATASET, progress_bar=False)
        clone = BC("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), dataset=DATASET, batch_size=16,
                   policy_kwargs={"net_arch": [32]}, seed=0)  # fmt: skip
        clone.learn(3)
        clone.save(root / "bc.zip")
        finetuned = CalQL("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), dataset=DATASET, batch_size=16,
                          policy_kwargs={"net_arch": [32]}, online_fraction=0.5, reward_scale=4.0, reward_bias=-2.0,
                          seed=0)  # fmt: skip
        finetuned.learn(FINETUNED_STEPS)
        finetuned.save(root / "finetuned.zip")
        finetuned.save_replay_buffer(root / "finetuned_buffer.pkl")
        spec = CollectionSpec(policy="noisy-regrasp-yaw", n_episodes=2, env_id="PandaForce-v0",
                              env_kwargs={"action_mode": "delta"})  # fmt: skip
        collect_dataset(spec, YAW_DATASET, progress_bar=False)
        chunked = CQL("MlpPolicy", gym.make("PandaForce-v0", action_mode="delta"), dataset=YAW_DATASET, action_chunk=CHUNK,
                      reward_scale=4.0, reward_bias=-2.0, seed=0, **TINY)  # fmt: skip
        chunked.learn(3)
        chunked.save(root / "chunked.zip")
        iql = IQL("MlpPolicy", gym.make("PandaForce-v0", action_mode="delta"), dataset=YAW_DATASET, gamma=0.999,
                  n_steps=5, seed=0, batch_size=16, policy_kwargs={"net_arch": [32]})  # fmt: skip
        iql.learn(3)
        iql.save(root / "iql.zip")
        yield root


def commands(root: Path) -> dict[str, list[str]]:
    """Each script's tiny run: a few gradient steps, one evaluation episode, logs in ``root``."""
    bc, tiny = str(root / "bc.zip"), json.dumps(TINY)
    return {
        "acting_noise": [bc, "--algo", "bc", "--env", "Panda-v0", "--seeds", "0", "--modes", "mean", "sample", "normal:0.1"],
        "action_drift": [bc, "--dataset-id", DATASET, "--kwargs", tiny, "--every", "1", "--probes", "2",
                         "--probe-states", "64", "--log-dir", str(root / "action_drift")],
        "advantage_weights": [str(root / "iql.zip"), "--dataset", YAW_DATASET, "--episodes", "2", "--weights", "0:1",
                              "50:10"],
        "bc_continued": [bc, "1", "2", "1e-3", "16", DATASET, "--eval-episodes", "1", "--log-dir", str(root / "bc_continued")],
        "closing_values": [str(root / "chunked.zip"), "--dataset", YAW_DATASET, "--episodes", "2"],
        "cql_from_clone": [bc, "2", "2", json.dumps({**TINY, "clip_backup": True}), DATASET, "--eval-episodes", "1",
                           "--log-dir", str(root / "cql_from_clone")],
        "grasp_stalls": [str(root / "iql.zip"), "--env", "Panda-v0", "--seeds", "0", "--dataset", YAW_DATASET,
                         "--episodes", "2"],
        "gripper_reopenings": [DATASET],
        "q_probe": ["2", tiny, "--dataset-id", DATASET, "--probe-states", "64", "--log-dir", str(root / "q_probe")],
        "values_vs_returns": [str(root / "finetuned.zip"), str(root / "finetuned_buffer.pkl"), "--offline-states", "64"],
    }  # fmt: skip


@pytest.fixture(scope="module")
def runs(inputs) -> dict[str, subprocess.CompletedProcess]:
    """Every script's tiny run, started together from the repository root; each one's exit status and output."""
    env = {**os.environ, "MINARI_DATASETS_PATH": str(inputs / "datasets")}
    outputs = {name: (inputs / f"{name}.stdout", inputs / f"{name}.stderr") for name in SCRIPTS}
    started = {}
    for name, args in commands(inputs).items():
        with open(outputs[name][0], "w") as stdout, open(outputs[name][1], "w") as stderr:
            command = [sys.executable, f"research/scripts/{name}.py", *args]
            started[name] = subprocess.Popen(command, cwd=ROOT, env=env, stdout=stdout, stderr=stderr)
    results = {}
    for name, process in started.items():
        returncode = process.wait(timeout=600)
        results[name] = subprocess.CompletedProcess(process.args, returncode, *(path.read_text() for path in outputs[name]))
    return results


def succeeded(runs, name: str) -> list[str]:
    """The lines ``name``'s run printed, once it has exited 0 (less pybullet's ``argv[0]=`` at each connection)."""
    result = runs[name]
    assert result.returncode == 0, result.stderr[-3000:]
    return [line for line in result.stdout.splitlines() if line != "argv[0]="]


def test_acting_noise_prints_success_per_mode_and_the_samples_statistics(runs):
    lines = succeeded(runs, "acting_noise")
    per_dimension = rf"\[{FLOAT}(?: {FLOAT}){{{ACTION_DIM - 1}}}\]"
    exploration = (rf"  wrist's 100-step change {FLOAT} deg \(RMS\), the noise's push on its target {FLOAT} deg; "
                   r"closings on a lying cylinder in [01] episodes, [01] within 20 deg of across it")  # fmt: skip
    expected = [
        r"mean: success [01]\.000 \([01]/1\)",
        exploration,
        r"sample: success [01]\.000 \([01]/1\)",
        exploration,
        rf"  std before tanh {per_dimension}",
        rf"  \|sample - mean\| {per_dimension}",
        rf"  finger sign flips \[{FLOAT} {FLOAT}\]",
        r"normal:0\.1: success [01]\.000 \([01]/1\)",
        exploration,
    ]
    assert len(lines) == len(expected), lines
    for line, pattern in zip(lines, expected, strict=True):
        assert re.fullmatch(pattern, line), line


def test_acting_noise_modes_give_sb3_action_noise():
    make_noise = load_script("acting_noise").make_noise
    assert make_noise("mean", 3) is None and make_noise("sample", 3) is None
    noise = make_noise("normal:0.5", 3)
    np.random.seed(0)
    draws = np.array([noise() for _ in range(2000)])
    assert draws.shape == (2000, 3) and abs(draws.std() - 0.5) < 0.05  # N(0, 0.5) per dimension
    correlated = make_noise("ou:0.5", 3)
    steps = np.array([correlated() for _ in range(200)])
    assert np.corrcoef(steps[:-1, 0], steps[1:, 0])[0, 1] > 0.5  # Ornstein-Uhlenbeck: correlated in time
    noise = make_noise("held:0.5", 3, hold=4)
    held = np.array([noise() for _ in range(12)])
    assert (held[:4] == held[0]).all() and (held[4:8] == held[4]).all() and not (held[4] == held[0]).any()
    pink = [np.array([make_noise("pink:0.5", 3, seq_len=100, seed=seed)() for _ in range(5)]) for seed in (7, 7, 8)]
    np.testing.assert_array_equal(pink[0], pink[1])  # seeded: the same episode seed, the same noise
    assert not np.array_equal(pink[0], pink[2])


def test_acting_noise_measures_the_wrists_100_step_change_from_the_joint_positions():
    script = load_script("acting_noise")
    observations = np.zeros((251, 29))
    observations[:, envs.OBSERVATION_SLICES["joint_positions"].start + script.WRIST] = 0.01 * np.arange(251)
    changes = script.wrist_changes(observations)
    assert len(changes) == 16 and np.allclose(changes, 1.0)  # windows from steps 0, 10, ..., 150; 0.01 rad a step
    assert np.allclose(script.window_sums(np.full(250, 0.01)), changes)  # the same from the step-to-step changes
    line = script.exploration_line({"wrist_changes": np.radians([3.0, -3.0]), "wrist_pushes": np.radians([0.0, 2.0]),
                                    "lying_closings": [[10.0, 75.0], [], [40.0]]})  # fmt: skip
    assert line == ("  wrist's 100-step change 3.0 deg (RMS), the noise's push on its target 1.4 deg; "
                    "closings on a lying cylinder in 2 episodes, 1 within 20 deg of across it")  # fmt: skip


def test_action_drift_prints_gradients_and_shifts(runs, inputs):
    lines = succeeded(runs, "action_drift")
    assert lines[0] == f"Logging to {inputs / 'action_drift'}"
    gradient = rf"dQ/da mean {FLOATS}, \|dQ/da\| mean {FLOATS}"
    expected = [rf"step 1: {gradient}", *(rf"step {step}: shift mean {FLOATS}, \|shift\| mean {FLOATS}" for step in (2, 3)),
                rf"step 3: {gradient}"]  # fmt: skip
    assert len(lines) == 1 + len(expected)
    for line, pattern in zip(lines[1:], expected, strict=True):
        assert re.fullmatch(pattern, line), line
    assert (inputs / "action_drift" / "progress.csv").exists()


def test_bc_continued_prints_success_every_k_steps(runs, inputs):
    lines = succeeded(runs, "bc_continued")
    assert lines[0] == f"Logging to {inputs / 'bc_continued'}"
    assert [re.fullmatch(rf"step (\d+): success rate {FLOAT}", line).group(1) for line in lines[1:]] == ["0", "1"]
    logged = pd.read_csv(inputs / "bc_continued" / "progress.csv")
    assert logged["train/n_updates"].tolist() == [1]  # a row per evaluation after training; STEPS is not rounded up to K


def test_cql_from_clone_prints_success_and_saves_the_model(runs, inputs):
    lines = succeeded(runs, "cql_from_clone")
    run_dir = Path(re.fullmatch(r"Logging to (.+)", lines[0]).group(1))
    assert run_dir.parent == inputs / "cql_from_clone" and re.fullmatch(r"\d+-\d+", run_dir.name)
    assert re.fullmatch(rf"step 0: success rate {FLOAT}", lines[1])
    assert re.fullmatch(rf"step 2: success rate {FLOAT}, policy std {FLOATS}", lines[2])
    assert lines[3:] == [f"saved {run_dir / 'model.zip'}"]
    model = load_script("cql_from_clone").ClippedBackupCQL.load(run_dir / "model.zip")  # the run's variant
    assert model._n_updates == 2 and model.batch_size == 16 and model.policy_kwargs["net_arch"] == [32]
    clone = BC.load(inputs / "bc.zip").actor.state_dict()
    for key, value in model.actor.state_dict().items():  # the clone's actor after 2 steps at CQL's actor rate, 3e-5
        th.testing.assert_close(value, clone[key], atol=1e-3, rtol=0)
    assert "train/cql_q_data" in pd.read_csv(run_dir / "progress.csv").columns


def test_gripper_reopenings_counts_the_episodes(runs):
    (line,) = succeeded(runs, "gripper_reopenings")
    # Episode 0 of the seed-0 collection loses the object and reopens; episode 1 succeeds without reopening.
    assert line == f"{DATASET}: 2 episodes, success rate 0.500, 1 with a reopening (0 of them successful)"


def test_closing_values_score_the_datas_closings_and_turns_on_a_lying_cylinder(runs, inputs):
    lines = succeeded(runs, "closing_values")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
        episodes = list(load_dataset(YAW_DATASET).iterate_episodes())
    angles = []  # the closings on a lying cylinder that leave room for a whole chunk of the data's actions
    for episode in episodes:
        steps = envs.pd_controller.closing_steps(episode.observations[:-1])
        angles += [envs.pd_controller.closing_angle(episode.observations[step]) for step in steps
                   if step + CHUNK <= len(episode.actions)]  # fmt: skip
    angles = [angle for angle in angles if angle is not None]
    assert angles, "the tiny data have no closing on a lying cylinder"
    assert lines[0] == (f"{inputs / 'chunked.zip'} (action_chunk {CHUNK}) on {YAW_DATASET}, 2 episodes: "
                        f"{len(angles)} closings on a lying cylinder")  # fmt: skip
    assert lines[1].split()[:3] == ["angle", "(deg)", "closings"]
    groups = {row.split()[0]: row.split()[1:] for row in lines[2:5]}
    assert list(groups) == ["0-30", "30-60", "60-90"]
    expected = [sum(low <= angle < high for angle in angles) for low, high in ((0, 30), (30, 60), (60, 90.01))]
    assert [int(row[0]) for row in groups.values()] == expected
    floor = -2.0 / (1 - 0.99)
    for row in groups.values():  # the data's returns lie between the floor and a lift at once
        assert row[1:] == ["-", "-", "-"] or (0 <= float(row[1]) <= 1 and floor - 0.05 <= float(row[2]) <= 2.0)
    assert re.match(rf"rank correlation over the closings: critic's value vs lifted ({FLOAT}|nan), vs data's return ",
                    lines[5]), lines[5]  # fmt: skip
    assert re.fullmatch(r"\d+ hovering states more than 20 deg from a grasping yaw: value turned towards it minus "
                        rf"away from it [+-]{FLOAT} \(std {FLOAT}, positive at {FLOAT} of the states\); the policy's "
                        rf"own wrist action turns towards it at {FLOAT}", lines[6]), lines[6]  # fmt: skip
    assert re.fullmatch(rf"the data's own actions there: (advantage of those that turn towards it minus away [+-]{FLOAT} "
                        r"\(\d+ towards, \d+ away\)|all \d+ turn (towards|away))", lines[7]), lines[7]  # fmt: skip
    assert re.fullmatch(rf"(the data's 25-step segments from there: advantage of those that end nearer a grasping yaw "
                        rf"minus farther [+-]{FLOAT} \(std {FLOAT}; \d+ nearer, \d+ farther\)|25-step segments: none "
                        rf"ends on a lying cylinder); rank correlation of V with the turn still needed "
                        rf"({FLOAT}|nan)", lines[8]), lines[8]  # fmt: skip
    assert len(lines) == 9


def test_closing_values_refuse_a_model_of_absolute_actions(inputs, tmp_path):
    SAC("MlpPolicy", gym.make("Panda-v0"), policy_kwargs={"net_arch": [8]}).save(tmp_path / "absolute.zip")
    with pytest.raises(SystemExit) as exit_:
        load_script("closing_values").main([str(tmp_path / "absolute.zip"), "--algo", "sac", "--dataset", YAW_DATASET])
    assert str(exit_.value.code).startswith("error: ") and "does not act in delta actions" in str(exit_.value.code)


def test_advantage_weights_reads_the_models_weights_and_others_over_the_datas_steps(runs, inputs):
    lines = succeeded(runs, "advantage_weights")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
        steps = sum(len(episode.actions) for episode in load_dataset(YAW_DATASET).iterate_episodes())
    assert lines[0] == f"{inputs / 'iql.zip'} on {YAW_DATASET}, 2 episodes, {steps} steps"
    assert re.fullmatch(rf"advantage quantiles 0\.01 / 0\.5 / 0\.99 / 0\.999 / max: (?:{SIGNED} / ){{4}}{SIGNED}", lines[1])
    assert re.fullmatch(rf"Q'\(s, a\) below the returns' floor 0: {FLOAT} of the steps, {FLOAT} below -1, the least {FLOAT}",
                        lines[2])  # fmt: skip
    weights = r": mean weight {}, at the clip {}, effective sample size {} of the samples"
    assert re.fullmatch(r"T 3 M 100 \(the model's\)" + weights.format(FLOAT, FLOAT, FLOAT), lines[3])
    # at temperature 0 every weight is 1, at the clip of 1: a clone's regression, every sample counting alike
    assert lines[4] == "T 0 M 1" + weights.format("1.00", "1.000", "1.000")
    assert re.fullmatch(r"T 50 M 10" + weights.format(FLOAT, FLOAT, FLOAT), lines[5])
    assert len(lines) == 6


def test_advantage_weights_effective_sample_size_and_clip_by_hand():
    line = load_script("advantage_weights").weights_line
    # weights 1, 1, 3: (1 + 1 + 3)^2 / (3 * (1 + 1 + 9)) = 25 / 33; clipped at 2: 16 / 18 of the samples, one at the clip
    advantage = np.array([0.0, 0.0, math.log(3.0)])
    assert line(advantage, 1.0, 100.0, own=True) == (
        "T 1 M 100 (the model's): mean weight 1.67, at the clip 0.000, effective sample size 0.758 of the samples"
    )
    assert line(advantage, 1.0, 2.0, own=False) == (
        "T 1 M 2: mean weight 1.33, at the clip 0.333, effective sample size 0.889 of the samples"
    )


def test_advantage_weights_refuse_a_bad_weight_setting(capsys):
    with pytest.raises(SystemExit):
        load_script("advantage_weights").main(["model.zip", "--weights", "50"])
    assert "must be TEMPERATURE:MAX_WEIGHT, such as 50:10, got '50'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        load_script("advantage_weights").main(["model.zip", "--weights", "50:0"])
    assert "needs a temperature >= 0 and a max weight > 0, got '50:0'" in capsys.readouterr().err


def test_grasp_stalls_count_the_datas_closings_by_alignment_and_the_policys_stalls(runs, inputs):
    lines = succeeded(runs, "grasp_stalls")
    assert lines[0] == f"{YAW_DATASET}, 2 episodes: open hand over an upright cylinder by alignment error"
    bands = [re.fullmatch(r"  ([\d.]+)-([\d.]+) cm: (\d+) steps, (-|[01]\.\d\d) close", line) for line in lines[1:5]]
    assert [(band[1], band[2]) for band in bands] == [("0", "1"), ("1", "1.5"), ("1.5", "2.5"), ("2.5", "4")]
    # the regrasping controller closes once aligned within 1 cm, and never before
    assert int(bands[0][3]) > 0 and bands[0][4] == "1.00"
    assert all(band[4] in ("-", "0.00") for band in bands[1:])
    match = re.fullmatch(rf"{re.escape(str(inputs / 'iql.zip'))} on Panda-v0, 1 episodes \(seeds 0-0\): success "
                         r"([01]\.00), ([01]) stalls", lines[5])  # fmt: skip
    assert match is not None, lines[5]
    if match[2] == "1":  # a stall, with its reading (an untrained policy seldom closes its hand on the object)
        assert re.fullmatch(r"  stalls at their last step: alignment error .+, critics' value of their action minus "
                            rf"closing {SIGNED} \(mean; positive at [01] of 1\)", lines[6])  # fmt: skip
    assert len(lines) == 6 + int(match[2])


def test_grasp_stalls_alignment_error_and_summary_by_hand():
    script = load_script("grasp_stalls")
    observation = np.zeros((1, 29))
    observation[0, envs.OBSERVATION_SLICES["ee_position"]] = [0.10, 0.20, 0.30]
    observation[0, envs.OBSERVATION_SLICES["object_position"]] = [0.104, 0.19, 0.305]
    np.testing.assert_allclose(script.alignment_errors(observation), [0.01])  # the largest offset, along y
    assert script.stalls_line([(0.004, 0.2, 0.1), (0.012, 0.4, -0.05), (0.02, 0.0, None)]) == (
        "  stalls at their last step: alignment error 1.2 cm (median; 0.4-2.0), gripper command +0.20 (mean; +0.00 to "
        "+0.40), critics' value of their action minus closing +0.025 (mean; positive at 1 of 2)"
    )


def test_alignment_figure_pools_a_rows_seeds(tmp_path, capsys):
    def record(rate, angles, never_closed=0):
        episodes = [{"seed": 50000 + i, "success": i < 1, "closing_angles": [None, *angles]} for i in range(2)]
        episodes += [{"seed": 50002 + i, "success": False, "closing_angles": []} for i in range(never_closed)]
        return {"tasks": {"PandaForce-v0": {"success_rate": rate, "episodes": episodes}}}

    paths = [tmp_path / name for name in ("cql-seed1.json", "cql-seed2.json", "pid-regrasp-aligned.json")]
    for path, settings in zip(paths, [(0.5, [85.0], 2), (0.3, [5.0, 45.0], 1), (0.6, [89.0])], strict=True):
        path.write_text(json.dumps(record(*settings)))
    main = load_script("alignment_figure").main
    main([*map(str, paths), "--output", str(tmp_path / "figure.png")])
    assert capsys.readouterr().out.splitlines() == [
        f"{tmp_path / 'figure.png'}: 2 rows (cql, pid-regrasp-aligned)",
        "cql: PandaForce-v0 0.40 (0.50 0.30), 3 failed without a closing; PandaForce-v0: 6 closings on a lying "
        "cylinder, 0.33 of them at 60-90 deg",
        "pid-regrasp-aligned: PandaForce-v0 0.60, 0 failed without a closing; PandaForce-v0: 2 closings on a lying "
        "cylinder, 1.00 of them at 60-90 deg",
    ]
    assert (tmp_path / "figure.png").read_bytes().startswith(b"\x89PNG")
    with pytest.raises(SystemExit) as exit_:
        main([str(paths[0]), "--task", "Panda-v0", "--output", str(tmp_path / "other.png")])
    assert exit_.value.code == f"error: {paths[0]}: no evaluation of Panda-v0 (sb3_cql.evaluate --output with --env Panda-v0)"
    assert not (tmp_path / "other.png").exists()


def test_q_probe_prints_q_at_data_perturbed_and_policy_actions(runs, inputs):
    lines = succeeded(runs, "q_probe")
    assert lines[0] == f"Logging to {inputs / 'q_probe'}"
    assert set(ast.literal_eval(lines[1].removeprefix("gripper data values "))) <= {-1.0, 1.0}
    expected = [r"Q data", *(rf"Q gripper x {scale}" for scale in ("0.99", "0.97", "0.9", "0.5")), r"Q arm \+N\(0,0.05\)"]
    for line, name in zip(lines[2:8], expected, strict=True):
        assert math.isfinite(float(re.fullmatch(rf"{name} ({FLOAT})", line).group(1))), line
    assert re.fullmatch(rf"Q policy mean {FLOAT}, Q policy sample {FLOAT}, policy std \[.+\]", lines[8])
    assert re.fullmatch(rf"Q policy mean with data gripper {FLOAT}", lines[9]) and len(lines) == 10


def test_values_vs_returns_scores_online_and_offline_states_against_their_returns_to_go(runs, inputs):
    lines = succeeded(runs, "values_vs_returns")
    # The untrained policy fails its one online episode, which the time limit cuts.
    assert re.fullmatch(rf"online: 1 episodes ended \(0 successful\), {FINETUNED_STEPS} transitions; "
                        r"[01] of the 1 failed ones reopen the gripper", lines[0])  # fmt: skip
    assert lines[1].split() == ["group", "states", "RTG", "Q(s,a)", "Q(s,pi)", "Q(s,pi)<RTG", "corr(Q(s,a),RTG)",
                                "median", "Q(s,a)", "Q(s,a)<RTG-100"]  # fmt: skip
    rows = {" ".join(line.split()[:2]): line.split()[2:] for line in lines[2:6]}
    assert list(rows) == ["online successful", "online failed", "offline successful", "offline failed"]
    assert rows["online successful"] == ["0"]
    assert lines[6:] == ["online successful, steps before the end: 0-99: none; 100-199: none; 200-399: none; 400-699: none"]
    floor = -2.0 / (1 - 0.99)  # rewards 4r - 2: a failed, cut episode earns -2 a step forever
    states, rtg, q_data, q_policy, below, correlation, median, far_below = rows["online failed"]
    assert (int(states), correlation) == (FINETUNED_STEPS, "nan")  # one return-to-go: no correlation
    assert float(rtg) == pytest.approx(floor, abs=0.05)  # printed with one decimal
    model = CalQL.load(inputs / "finetuned.zip")
    model.load_replay_buffer(inputs / "finetuned_buffer.pkl")
    online = model.replay_buffer.online
    observations, actions = (th.as_tensor(array[:FINETUNED_STEPS, 0]) for array in (online.observations, online.actions))
    with th.no_grad():
        expected = th.min(*model.critic(observations, actions)).mean().item()
        policy = th.min(*model.critic(observations, model.actor(observations, deterministic=True)))
    assert float(q_data) == pytest.approx(expected, abs=0.06)  # printed with one decimal
    critic = th.min(*model.critic(observations, actions)).detach()
    assert float(median) == pytest.approx(np.median(critic.numpy()), abs=0.06)
    assert float(far_below) == pytest.approx((critic < floor - 100).float().mean().item(), abs=6e-4)
    assert float(below) == pytest.approx((policy < floor).float().mean().item(), abs=6e-4)
    # The dataset's two episodes: the successful one earns more than the floor from every state, the failed one not.
    assert int(rows["offline successful"][0]) + int(rows["offline failed"][0]) == 64
    assert float(rows["offline successful"][1]) > floor + 0.05
    assert float(rows["offline failed"][1]) == pytest.approx(floor, abs=0.05)


def test_values_vs_returns_bins_a_successful_episodes_states_by_steps_before_its_end(inputs):
    script = load_script("values_vs_returns")
    model = CalQL.load(inputs / "finetuned.zip")
    model.load_replay_buffer(inputs / "finetuned_buffer.pkl")
    online = script.with_returns_to_go(model, model.replay_buffer.online)
    episode = np.arange(250)  # taken as one episode: its last 100 states, the 100 before, then 50
    line = script.before_success(model, online, [episode])
    counts = [int(count) for count in re.findall(r"\((\d+)\)", line)]
    assert counts == [100, 100, 50] and line.endswith("400-699: none")
    rtg = [float(value) for value in re.findall(rf"RTG ({FLOAT})", line)]
    expected = [online.returns_to_go[rows, 0].mean() for rows in (episode[150:], episode[50:150], episode[:50])]
    np.testing.assert_allclose(rtg, expected, atol=0.06)


def test_values_vs_returns_scores_a_chunked_model_at_the_stored_chunks(inputs, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
    script = load_script("values_vs_returns")
    model = CQL.load(inputs / "chunked.zip")
    chunks = model.load_offline_data()
    offline = script.with_returns_to_go(model, chunks)
    rows = np.arange(0, chunks.size(), 7)
    np.testing.assert_array_equal(script.stored_actions(model, offline, rows), chunks.chunk_actions(rows))
    _, q_data, _ = script.values(model, offline, rows)
    observations = th.as_tensor(chunks.observations[rows, 0])
    with th.no_grad():
        expected = th.min(*model.critic(observations, th.as_tensor(chunks.chunk_actions(rows)))).numpy().ravel()
    np.testing.assert_allclose(q_data, expected, rtol=1e-6)


def test_a_reopening_counts_only_gripper_commands_held_for_20_steps():
    held = load_script("values_vs_returns").held
    reopens = load_script("gripper_reopenings").reopens
    opened, closed = np.ones(30), -np.ones(30)
    flip = np.concatenate([opened, closed, np.full(19, 0.5), closed])  # a noise flip open while closed
    np.testing.assert_array_equal(held(flip), np.concatenate([opened, closed, closed]))
    assert reopens(flip) and not reopens(held(flip))
    assert reopens(held(np.concatenate([opened, closed, np.full(20, 0.5), closed])))  # a regrasp
    assert len(held(np.ones(19))) == 0


def test_finetune_record_reads_a_zoo_fine_tuning_folder(inputs, tmp_path, capsys):
    """A zoo run folder made of the fixture's fine-tuning (one 700-step episode online) and a hand-written
    evaluation and monitor file."""
    run = tmp_path / "PandaForce-v0_1"
    run.mkdir()
    (run / f"rl_model_replay_buffer_{FINETUNED_STEPS}_steps.pkl").write_bytes((inputs / "finetuned_buffer.pkl").read_bytes())
    np.savez(run / "evaluations.npz", timesteps=np.array([350, 700]), successes=np.array([[1, 0], [1, 1]]))
    (run / "0.monitor.csv").write_text('#{"t_start": 0}\nr,l,t,is_success\n0.0,700,1.0,False\n1.0,300,2.0,True\n')
    load_script("finetune_record").main([str(run), "--output", str(tmp_path / "curves.png"), "--block", "500"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[:2] == [f"{tmp_path / 'curves.png'}: evaluations of 1 runs",
                         f"{run}: evaluations at 350, 700 env steps: 0.50 1.00"]  # fmt: skip
    none = "closings on a lying cylinder in 0, 0 within 20 deg of across it (0 of them succeeded)"
    assert lines[2] == f"  0-500 env steps: 0 of 0 online episodes succeeded; {none}"
    closings = r"closings on a lying cylinder in [01], [01] within 20 deg of across it \(0 of them succeeded\)"
    assert re.fullmatch(rf"  500-1,000 env steps: 1 of 2 online episodes succeeded; {closings}", lines[3])
    assert len(lines) == 4 and (tmp_path / "curves.png").stat().st_size > 0


def test_values_vs_returns_says_in_one_line_that_a_model_is_missing(tmp_path):
    with pytest.raises(SystemExit) as exit_:
        load_script("values_vs_returns").main([str(tmp_path / "missing.zip"), str(tmp_path / "missing.pkl")])
    assert str(exit_.value.code).startswith("error: ") and "\n" not in str(exit_.value.code)


def test_training_log_reads_what_a_training_printed_at_the_chosen_steps(tmp_path, capsys):
    """A real IQL training at verbose 1 (tables every 2 gradient steps), its stdout saved: the script picks the table
    nearest each multiple of --every and prints the keys' values as SB3 printed them, and refuses a missing key."""
    model = IQL("MlpPolicy", gym.make("Pendulum-v1"), dataset=random_rollouts(gym.make("Pendulum-v1"), 50), batch_size=8,
                policy_kwargs={"net_arch": [8]}, verbose=1, seed=0)  # fmt: skip
    model.learn(6, log_interval=2)
    log = tmp_path / "train.log"
    log.write_text(capsys.readouterr().out)
    script = load_script("training_log")
    tables = script.read_tables(log.read_text())
    assert [table["time/total_timesteps"] for table in tables] == ["2", "4", "6"]
    assert [table["train/n_updates"] for table in tables] == ["2", "4", "6"]
    script.main([str(log), "--keys", "train/n_updates", "train/critic_loss", "--every", "3"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == str(log)
    assert [line.split(":")[0] for line in lines[1:]] == ["  step 2", "  step 6"]  # 3 is nearest 2 (first), 6 is 6
    assert lines[2] == f"  step 6: train/n_updates 6, train/critic_loss {tables[-1]['train/critic_loss']}"
    with pytest.raises(SystemExit) as exit_:
        script.main([str(log), "--keys", "train/nothing"])
    assert str(exit_.value.code).startswith(f"{log}: no train/nothing in its tables; they have ")
    with pytest.raises(SystemExit) as exit_:
        script.main([str(tmp_path / "missing.log")])
    assert "missing.log: cannot read it" in str(exit_.value.code)


@pytest.mark.parametrize(
    "name", [*SCRIPTS, "alignment_figure", "finetune_drift", "finetune_record", "training_log", "suite_training_log"]
)
def test_help_shows_the_usage(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        load_script(name).main(["--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: python research/scripts/{name}.py")


@pytest.mark.parametrize(
    ("name", "args", "message"),
    [
        ("bc_continued", ["bc.zip", "many", "2", "1e-3", "16", DATASET], "argument STEPS: invalid int value: 'many'"),
        ("bc_continued", ["bc.zip", "10", "0", "1e-3", "16", DATASET], "argument K: must be a positive integer, got 0"),
        ("cql_from_clone", ["bc.zip", "10", "2", "{"], "argument KWARGS_JSON: not JSON"),
        ("cql_from_clone", ["bc.zip", "10", "2", '{"batch": 16}'], "argument KWARGS_JSON: not CQL keywords: batch"),
        ("cql_from_clone", ["bc.zip", "10", "2", '{"clip_backup": true, "mean_backup": true}'], "at most one of"),
        ("q_probe", ["10"], "the following arguments are required: KWARGS_JSON"),
        ("q_probe", ["10", "[16]"], "argument KWARGS_JSON: must be a JSON object"),
        ("action_drift", ["bc.zip", "--kwargs", '{"seed": 2}'], "argument --kwargs: not CQL keywords: seed"),
        ("gripper_reopenings", [], "the following arguments are required: DATASET_ID"),
        ("acting_noise", ["bc.zip", "--modes", "normal"], "argument --modes: unknown mode 'normal'"),
        ("acting_noise", ["bc.zip", "--seeds", "9-1"], "argument --seeds: '9-1' is an empty range"),
        ("values_vs_returns", ["model.zip"], "the following arguments are required: buffer"),
        ("closing_values", ["model.zip", "--episodes", "0"], "argument --episodes: must be a positive integer, got 0"),
        ("alignment_figure", ["record.json"], "the following arguments are required: --output"),
        ("finetune_record", ["run", "--output", "f.png", "--block", "0"], "argument --block: must be a positive integer"),
        ("finetune_record", ["a", "b", "--output", "f.png", "--labels", "x"], "--labels: 1 names for 2 runs"),
        ("values_vs_returns", ["model.zip", "buffer.pkl", "--offline-states", "0"], "must be a positive integer"),
        ("suite_training_log", ["suite", "lunar-mixture", "out", "--keywords", "[1]"], "must be a JSON object"),
        ("suite_training_log", ["suite", "lunar-mixture", "out", "--keywords", '{"cql_alhpa": 1}'], "cql_alhpa"),
        ("suite_training_log", ["suite", "lunar", "out"], "argument dataset: invalid choice: 'lunar'"),
    ],
)
def test_a_bad_argument_is_a_usage_error(name, args, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        load_script(name).main(args)
    assert exit_.value.code == 2
    usage, error = capsys.readouterr().err.strip().rsplit("\n", 1)
    assert usage.startswith(f"usage: python research/scripts/{name}.py") and message in error


def test_reopening_is_an_open_command_after_the_first_close():
    reopens = load_script("gripper_reopenings").reopens
    assert not reopens(np.array([1.0, 1.0, -1.0, -1.0]))  # closes once
    assert not reopens(np.array([1.0, 1.0]))  # never closes
    assert reopens(np.array([1.0, -1.0, 1.0, -1.0]))  # regrasps
    assert reopens(np.array([-1.0, 1.0]))  # starts closed


def tiny_cql(variant, inputs):
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
        return variant("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), dataset=DATASET, seed=0, batch_size=16,
                       policy_kwargs={"net_arch": [32]}, reward_scale=0.001, reward_bias=-0.0005)  # fmt: skip


def test_clip_backup_clamps_the_next_state_values_to_the_possible_returns(inputs):
    model = tiny_cql(load_script("cql_from_clone").ClippedBackupCQL, inputs)
    data = model.replay_buffer.sample(256)
    policy = model.actor.get_action_dist_params(data.next_observations)[:2]
    with th.no_grad():
        th.manual_seed(0)
        clipped = model.next_state_values(data.next_observations, policy, th.ones(1))
        th.manual_seed(0)
        plain = CQL.next_state_values(model, data.next_observations, policy, th.ones(1))
    bound = 0.0005 / (1 - model.gamma)  # rewards -0.0005 or 0.0005
    assert plain.abs().max() > bound  # the untrained critics' values exceed the bound
    th.testing.assert_close(clipped, plain.clamp(-bound, bound))


def test_mean_backup_scores_the_mean_action(inputs):
    model = tiny_cql(load_script("cql_from_clone").MeanBackupCQL, inputs)
    data = model.replay_buffer.sample(256)
    mean_actions, log_std = model.actor.get_action_dist_params(data.next_observations)[:2]
    with th.no_grad():
        values = model.next_state_values(data.next_observations, (mean_actions, log_std), th.ones(1))
        expected = th.cat(model.critic_target(data.next_observations, th.tanh(mean_actions)), 1).min(1, keepdim=True).values
    th.testing.assert_close(values, expected, atol=1e-4, rtol=0)


def test_capped_iql_is_iql_with_a_ceiling_of_1_and_loads_an_iql_model(inputs, tmp_path):
    from research.iql_variants import CappedIQL

    model = tiny_cql(CappedIQL, inputs)
    with th.no_grad():
        model.value_net.v_net[-1].bias.fill_(5.0)  # values far above any return of a 0/1 reward
    data = model.replay_buffer.sample(256)
    with th.no_grad():
        capped = model.compute_target(data, model.gamma)
        model.target_ceiling = None
        plain = model.compute_target(data, model.gamma)
    assert plain.max() > 1.0
    th.testing.assert_close(capped, plain.clamp(max=1.0))
    iql = tiny_cql(IQL, inputs)
    iql.save(tmp_path / "iql.zip")
    loaded = CappedIQL.load(tmp_path / "iql.zip", target_ceiling=0.5)
    assert isinstance(loaded, CappedIQL) and loaded.target_ceiling == 0.5


def test_offline_anchor_iql_anchors_the_actor_to_the_offline_rows_of_a_fine_tuning_batch(inputs):
    """With online transitions, the ddpg_awr loss with the online rows' imitation weights 0 and the offline rows'
    normalised over them; with none yet, IQL's own loss."""
    import copy

    from research.iql_variants import OfflineAnchorIQL
    from sb3_cql.common import MixedReplayBuffer

    model = tiny_cql(OfflineAnchorIQL, inputs)
    model.actor_loss_type = "ddpg_awr"
    weights = th.linspace(0.5, 2.0, 16)
    data = model.replay_buffer.sample(16)
    th.testing.assert_close(model.actor_loss(data, weights, {}), IQL.actor_loss(model, data, weights, {}))
    offline = model.replay_buffer
    model.replay_buffer = MixedReplayBuffer(offline, copy.deepcopy(offline), online_fraction=0.25)
    data = model.replay_buffer.sample(16)  # 12 offline rows, then 4 online
    imitation = th.cat([weights[:12] / weights[:12].mean() * 16 / 12, th.zeros(4)])
    expected = IQL.ddpg_actor_loss(model, data, imitation, {})
    th.testing.assert_close(model.actor_loss(data, weights, {}), expected)
    assert not th.allclose(expected, IQL.actor_loss(model, data, weights, {}))


def test_success_anchor_iql_imitates_the_online_rows_of_episodes_that_succeeded(inputs, tmp_path):
    """Fine-tuned for one episode online from a saved IQL model: the buffers hold returns-to-go, and the actor's loss
    is the ddpg_awr loss with the online rows' imitation weights 1 where the return-to-go is above 0, else 0."""
    from research.iql_variants import SuccessAnchorIQL
    from sb3_cql.common import ReturnToGoReplayBuffer

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
        iql = IQL("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), dataset=DATASET, seed=0, batch_size=16,
                  policy_kwargs={"net_arch": [32]})  # fmt: skip
        iql.save(tmp_path / "iql.zip")
        model = SuccessAnchorIQL.load(tmp_path / "iql.zip", env=gym.make("Panda-v0", action_mode="delta"),
                                      actor_loss_type="ddpg_awr", online_fraction=0.5, learning_starts=0, seed=0)  # fmt: skip
        model.learn(FINETUNED_STEPS)
    buffer = model.replay_buffer
    assert isinstance(buffer.offline, ReturnToGoReplayBuffer) and isinstance(buffer.online, ReturnToGoReplayBuffer)
    assert buffer.online.size() == FINETUNED_STEPS
    buffer.online.returns_to_go[:FINETUNED_STEPS:2] = 0.5  # as if every other row's episode had succeeded
    data = buffer.sample(16)  # 8 offline rows, then 8 online
    assert set(data.returns_to_go[8:, 0].tolist()) == {0.0, 0.5}
    weights = th.linspace(0.5, 2.0, 16)
    imitation = th.cat([weights[:8] / weights[:8].mean(), (data.returns_to_go[8:, 0] > 0).float()])
    th.testing.assert_close(model.actor_loss(data, weights, {}), IQL.ddpg_actor_loss(model, data, imitation, {}))
    with pytest.raises(SettingError, match="reward_bias must be 0"):
        SuccessAnchorIQL.load(tmp_path / "iql.zip", reward_bias=-0.5)


@pytest.mark.parametrize("ceiling", [float("nan"), "1", -1.0])
def test_capped_iql_refuses_a_ceiling_that_is_not_a_finite_number_above_the_floor(inputs, ceiling):
    from research.iql_variants import CappedIQL

    with pytest.raises(SettingError, match="target_ceiling"), pytest.MonkeyPatch.context() as patch:
        patch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
        CappedIQL("MlpPolicy", gym.make("Panda-v0", action_mode="delta"), dataset=DATASET, batch_size=16,
                  policy_kwargs={"net_arch": [32]}, target_floor=0.0, target_ceiling=ceiling)  # fmt: skip


def test_suite_training_log_keeps_the_multipliers_log_the_model_and_its_score(tmp_path):
    """A tiny run on the suite's weak MountainCarContinuous-v0 data: the training log holds the learned weight's
    multiplier and the gap it answers to, beside the model and the score of its 20 episodes."""
    import pandas as pd

    script = load_script("suite_training_log")
    assert script.main([str(tmp_path / "suite"), "mountaincar-weak", str(tmp_path / "out"), "--steps", "500",
                        "--keywords", '{"batch_size": 16}']) == 0  # fmt: skip
    log = pd.read_csv(tmp_path / "out" / "progress.csv")
    assert list(log["train/n_updates"]) == [500]
    assert 0 < log["train/cql_alpha_prime"].iloc[0] < 1  # the gap under its target of 10: the multiplier eased
    assert log["train/cql_gap"].iloc[0] < 10
    score = json.loads((tmp_path / "out" / "score.json").read_text())
    assert len(score["successes"]) == 20 and score["score"] == pytest.approx(np.mean(score["successes"]))
    assert CQL.load(tmp_path / "out" / "model.zip").batch_size == 16


def test_finetune_drift_reads_the_actor_against_its_critics_and_the_closings(inputs, tmp_path, monkeypatch, capsys):
    """The fixture's IQL model fine-tuned one 700-step episode online (ddpg_awr, half the batch online), its
    checkpoint and online transitions read against the start: the start's row is all zeros, the checkpoint's changes
    are the actions' by hand, and the data's closings are counted as the controller made them."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(inputs / "datasets"))
    script = load_script("finetune_drift")
    model = IQL.load(inputs / "iql.zip", env=gym.make("PandaForce-v0", action_mode="delta"), actor_loss_type="ddpg_awr",
                     online_fraction=0.5, learning_starts=0, seed=0)  # fmt: skip
    model.learn(FINETUNED_STEPS)
    model.save(tmp_path / "tuned.zip")
    model.save_replay_buffer(tmp_path / "tuned.pkl")
    script.main([str(inputs / "iql.zip"), str(tmp_path / "tuned.zip"), "--buffer", str(tmp_path / "tuned.pkl"),
                 "--states", "64", "--window", "500"])  # fmt: skip
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["checkpoint", "|da|", "arm"]
    assert re.fullmatch(rf"\S+/iql\.zip +0\.000 +0\.000 +\+0\.0000 +{SIGNED} +{FLOAT}", lines[1]), lines[1]
    row = lines[2].split()
    assert row[0].endswith("/tuned.zip")
    start, tuned = IQL.load(inputs / "iql.zip"), IQL.load(tmp_path / "tuned.zip")
    observations, _ = script.probe_states(start.load_offline_data(), model.replay_buffer.online, 64)
    actions = [policy.predict(observations.numpy(), deterministic=True)[0] for policy in (start, tuned)]
    change = np.abs(actions[1] - actions[0])
    assert (row[1], row[2]) == (f"{change[:, :7].mean():.3f}", f"{change[:, 7:].mean():.3f}")
    assert float(row[1]) > 0 and float(row[2]) > 0  # the actor moved, its arm and its fingers
    assert 0 <= float(row[5]) <= 1
    assert lines[3].split()[:4] == ["closings", "at", "50-90", "deg"]
    angles = [angle for episode in load_dataset(YAW_DATASET).iterate_episodes()
              for angle in envs.pd_controller.closing_angles(episode.observations)]  # fmt: skip
    closings = sum(angle is not None and angle >= 50 for angle in angles)
    assert lines[4].split()[:4] == ["offline", "data", "2", str(closings)]
    assert lines[5].split()[:4] == ["online", "0-500", "1", lines[5].split()[3]] and len(lines) == 6


def test_finetune_drift_anchor_share_is_the_anchors_part_of_the_gradient(inputs):
    """No anchor: a share of 0; an anchor a million times the critics' normalised value: a share near 1."""
    script = load_script("finetune_drift")
    model = IQL.load(inputs / "iql.zip", actor_loss_type="ddpg_awr")
    observations, actions = th.zeros(8, model.observation_space.shape[0]), th.full((8, ACTION_DIM), 0.5)
    model.actor_bc_weight = 0.0
    assert script.anchor_share(model, observations, actions) == 0.0
    model.actor_bc_weight = 1e6
    assert script.anchor_share(model, observations, actions) > 0.99


def test_finetune_drift_refuses_a_missing_file_on_one_line(tmp_path):
    with pytest.raises(SystemExit) as exit_:
        load_script("finetune_drift").main([str(tmp_path / "a.zip"), str(tmp_path / "b.zip"), "--buffer", "c.pkl"])
    assert exit_.value.code == f"error: no file {tmp_path / 'a.zip'}"


def test_finetune_drift_refuses_a_file_that_is_not_a_model_on_one_line(inputs, tmp_path):
    (tmp_path / "a.zip").write_text("not a model")
    with pytest.raises(SystemExit) as exit_:
        load_script("finetune_drift").main([str(tmp_path / "a.zip"), str(inputs / "iql.zip"), "--buffer",
                                            str(inputs / "finetuned_buffer.pkl")])  # fmt: skip
    assert str(exit_.value.code).startswith("error: ") and "\n" not in str(exit_.value.code)


def test_finetune_resumable_counts_segments_and_refuses_a_second_process_on_the_same_folder(tmp_path):
    import fcntl

    script = [sys.executable, "research/scripts/finetune_resumable.py", "model.zip", str(tmp_path), "--seed", "1",
              "--steps", "30000"]  # fmt: skip
    for segment, steps in (("PandaForce-v0_1", 20_000), ("PandaForce-v0_2", 10_000)):
        folder = tmp_path / "iql" / segment
        folder.mkdir(parents=True)
        (folder / f"rl_model_{steps}_steps.zip").write_bytes(segment.encode())
        (folder / f"rl_model_replay_buffer_{steps}_steps.pkl").write_bytes(b"")
    (tmp_path / "iql" / "PandaForce-v0_2" / "rl_model_20000_steps.zip").write_bytes(b"no buffer beside it")
    with open(tmp_path / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        held = subprocess.run(script, cwd=ROOT, capture_output=True, text=True)
    assert held.returncode == 2 and held.stdout == ""
    assert held.stderr.strip().splitlines() == [f"{tmp_path} is being fine-tuned by another process; wait for it or stop it first"]
    assert not (tmp_path / "final.zip").exists()
    done = subprocess.run(script, cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "30000 steps done; final model" in done.stdout
    assert (tmp_path / "final.zip").read_bytes() == b"PandaForce-v0_2"


def test_arm_exploration_noise_explores_in_the_arm_joints_only():
    from research.exploration import ArmExplorationNoise

    env = gym.make("Panda-v0", action_mode="delta")
    model = IQL("MlpPolicy", env, dataset=random_rollouts(env, 50), seed=0, batch_size=8, policy_kwargs={"net_arch": [32]})
    callback = ArmExplorationNoise(pink_std=0.5)
    callback.init_callback(model)
    draws = np.array([model.action_noise() for _ in range(200)])
    assert draws.shape == (200, ACTION_DIM)
    assert (draws[:, 7:] == 0).all()  # the two fingers
    assert (draws[:, :7].std(axis=0) > 0.05).all()  # each arm joint explores
    model.action_noise.reset()  # a new episode's sequence, masked as the first
    assert (model.action_noise()[7:] == 0).all()
