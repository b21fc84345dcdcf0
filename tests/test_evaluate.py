"""python -m sb3_cql.evaluate: the action mode read from the model, per-episode seeds, and bad input as one-line errors."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from startup import interrupt_while_starting

from sb3_cql import BC
from sb3_cql.evaluate import env_kwargs_for, episode_successes, format_seeds, load_policy, main, parse_seeds, success_rate

ROOT = Path(__file__).resolve().parents[1]
TINY = {"net_arch": [32]}
ERROR = "python -m sb3_cql.evaluate: error: "
DELTA_SPACE = "Box(-1.0, 1.0, (9,), float32)"


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    """Tiny saved models: BC trained a few steps in delta actions, an untrained SAC in absolute actions, a Pendulum
    SAC; and files that are no model."""
    folder = tmp_path_factory.mktemp("models")
    env = gym.make("Panda-v0", action_mode="delta")
    buffer = ReplayBuffer(64, env.observation_space, env.action_space)
    rng = np.random.default_rng(0)
    for _ in range(64):
        observation = rng.normal(size=env.observation_space.shape).astype(np.float32)
        buffer.add(observation, observation, env.action_space.sample(), np.array([0.0]), np.array([False]), [{}])
    bc = BC("MlpPolicy", env, dataset=buffer, batch_size=16, policy_kwargs=TINY, seed=0)
    bc.learn(2)
    bc.save(folder / "bc_delta")
    env.close()
    absolute = gym.make("Panda-v0")
    SAC("MlpPolicy", absolute, buffer_size=1, policy_kwargs=TINY, seed=0).save(folder / "sac_absolute")
    absolute.close()
    SAC("MlpPolicy", "Pendulum-v1", buffer_size=1, policy_kwargs=TINY, seed=0).save(folder / "pendulum")
    (folder / "text.zip").write_text("not a model\n")
    zipped = (folder / "bc_delta.zip").read_bytes()
    (folder / "truncated.zip").write_bytes(zipped[: len(zipped) // 2])
    return {path.stem: path for path in folder.iterdir()}


def error_lines(capsys) -> list[str]:
    return capsys.readouterr().err.splitlines()


def test_a_model_is_evaluated_in_the_action_mode_it_was_trained_in(models, capsys):
    bc, sac = (
        load_policy(str(models[name]), algo, "Panda-v0") for name, algo in (("bc_delta", "bc"), ("sac_absolute", "sac"))
    )
    assert env_kwargs_for(bc, "PandaForce-v0") == {"action_mode": "delta"}
    assert env_kwargs_for(sac, "PandaPerturbed-v0", {"object_mass": 0.2}) == {"object_mass": 0.2, "action_mode": "absolute"}
    assert env_kwargs_for(bc, "Panda-v0", {"action_mode": "delta"}) == {"action_mode": "delta"}
    main([str(models["bc_delta"]), "--algo", "bc", "--env", "Panda-v0", "-n", "1"])
    assert capsys.readouterr().out.splitlines()[-1] == "Panda-v0: success rate 0.000 over 1 episodes (seed 0, delta actions)"


def test_an_action_mode_that_is_not_the_models_is_refused(models, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([str(models["bc_delta"]), "--algo", "bc", "--env", "Panda-v0", "--env-kwargs", "action_mode:'absolute'"])
    assert exit_.value.code == 2
    (line,) = error_lines(capsys)
    assert line.startswith(ERROR + str(models["bc_delta"]))
    assert f"action space {DELTA_SPACE} is that of action_mode 'delta', not that of the action_mode 'absolute'" in line
    assert "Box([-2.9671 -1.8326" in line  # the absolute space: the joint limits


def test_success_rate_refuses_a_policy_made_for_other_spaces(models):
    bc = load_policy(str(models["bc_delta"]), "bc", "Panda-v0")
    delta_is_not_absolute = (
        r"action space Box\(-1.0, 1.0, \(9,\), float32\) is not that of Panda-v0 \(action_mode 'absolute'\)"
    )
    with pytest.raises(ValueError, match=delta_is_not_absolute):
        success_rate(bc, "Panda-v0", n_episodes=1)
    with pytest.raises(ValueError, match="action space"):
        success_rate(bc, "Panda-v0", env_kwargs={"action_mode": "absolute"}, seeds=[0])
    sac = load_policy(str(models["sac_absolute"]), "sac", "Panda-v0")
    with pytest.raises(ValueError, match=r"is not that of PandaForce-v0 \(action_mode 'delta'\)"):
        success_rate(sac, "PandaForce-v0", n_episodes=1, env_kwargs={"action_mode": "delta"})
    pendulum = load_policy(str(models["pendulum"]), "sac", "Panda-v0")
    with pytest.raises(ValueError, match=r"observation space .*\(3,\).* is not that of Panda-v0"):
        success_rate(pendulum, "Panda-v0", n_episodes=1)


def test_the_pd_controllers_act_in_absolute_actions_unless_told(capsys):
    main(["pid", "--env", "Panda-v0", "--seeds", "0"])
    main(["pid", "--env", "Panda-v0", "--seeds", "0", "--env-kwargs", "action_mode:'delta'"])
    assert capsys.readouterr().out.splitlines()[-2:] == [
        "Panda-v0: success rate 1.000 over 1 episodes (seeds 0, absolute actions)",
        "Panda-v0: success rate 1.000 over 1 episodes (seeds 0, delta actions)",
    ]


class Recorder:
    """A policy that records the observations it acts on."""

    def __init__(self, policy):
        self.policy = policy
        self.observations = []

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        self.observations.append(observation)
        return self.policy.predict(observation, state, episode_start, deterministic=deterministic)


def test_each_episode_is_reset_with_its_seed():
    seeds = [7, 3, 7]
    recorder = Recorder(load_policy("pid", None, "PandaPerturbed-v0"))
    successes = episode_successes(recorder, "PandaPerturbed-v0", seeds)
    controller = load_policy("pid", None, "PandaPerturbed-v0")
    env = gym.make("PandaPerturbed-v0")
    by_hand, observations, first_observations = [], [], []
    for seed in seeds:  # as any other tool replays them
        observation, _ = env.reset(seed=seed)
        first_observations.append(observation)
        terminated = truncated = False
        while not (terminated or truncated):
            observations.append(observation)
            observation, _, terminated, truncated, info = env.step(controller.predict(observation)[0])
        by_hand.append(info["is_success"])
    env.close()
    assert successes == by_hand
    np.testing.assert_array_equal(np.stack(recorder.observations), np.stack(observations))
    np.testing.assert_array_equal(first_observations[0], first_observations[2])
    assert not np.array_equal(first_observations[0], first_observations[1])  # another seed, another object pose
    assert success_rate(controller, "PandaPerturbed-v0", seeds=seeds) == np.mean(by_hand)


def test_the_new_pd_controllers_are_evaluated_by_name(capsys):
    main(["pid-regrasp-yaw", "--env", "Panda-v0", "--seeds", "0", "--env-kwargs", "action_mode:'delta'"])
    main(["pid-regrasp-aligned", "--env", "Panda-v0", "-n", "1"])
    assert capsys.readouterr().out.splitlines()[-2:] == [
        "Panda-v0: success rate 1.000 over 1 episodes (seeds 0, delta actions)",
        "Panda-v0: success rate 1.000 over 1 episodes (seed 0, absolute actions)",
    ]


def test_a_controllers_random_yaws_are_seeded_with_each_episodes_seed(monkeypatch):
    controller = load_policy("pid-regrasp-yaw", None, "Panda-v0")
    predict, first_yaws = controller.predict, []

    def recording(observation, state=None, episode_start=None, deterministic=True):
        action, state = predict(observation, state, episode_start, deterministic)
        if episode_start[0]:
            first_yaws.append(state[0][0])
        return action, state

    monkeypatch.setattr(controller, "predict", recording)
    assert episode_successes(controller, "Panda-v0", [5, 6, 5]) == [True, True, True]
    assert first_yaws[0] == first_yaws[2] != first_yaws[1]  # an episode is replayed by its seed, yaw included


def test_alignment_shows_how_the_fingers_closed_on_the_lying_cylinder(tmp_path, capsys):
    for name in ("pid-regrasp-aligned", "pid-regrasp"):
        main([name, "--env", "PandaForce-v0", "--seeds", "0", "--alignment", "--output", str(tmp_path / f"{name}.json")])
    lines = capsys.readouterr().out.splitlines()
    records = {name: json.loads((tmp_path / f"{name}.json").read_text()) for name in ("pid-regrasp-aligned", "pid-regrasp")}
    for name, record in records.items():
        (episode,) = record["tasks"]["PandaForce-v0"]["episodes"]
        assert episode["seed"] == 0 and record["model"] == name
        assert episode["closing_angles"][0] is None  # the first grasp, of the upright cylinder
        angles = [angle for angle in episode["closing_angles"] if angle is not None]
        assert angles, "the knocked-out cylinder was never grasped again"
        if name == "pid-regrasp-aligned":
            assert all(angle >= 80 for angle in angles)
        else:  # the fixed yaw first closes along the axis of the cylinder as it fell
            assert angles[0] < 10
        across = sum(angle >= 80 for angle in angles)
        line = lines[[line.startswith("PandaForce-v0: success") for line in lines].index(True) + 1]
        assert line.endswith(f"80-90: {across} ({len(angles)} in 1 episodes; 1 on an upright cylinder)"), line
        lines = lines[lines.index(line) + 1 :]
    with pytest.raises(SystemExit):
        main(["pid", "--env", "Panda-v0", "-n", "1", "--alignment"])
    assert "--alignment and --output need --seeds" in capsys.readouterr().err


def test_seeds_are_a_range_or_a_list(capsys):
    assert parse_seeds("50000-50099") == range(50000, 50100)
    assert parse_seeds("42") == range(42, 43)
    assert format_seeds(list(range(50000, 50100))) == "50000-50099"
    assert format_seeds([3, 17, 42]) == "3 17 42"
    main(["pid", "--env", "Panda-v0", "--seeds", "10-11", "5"])
    main(["pid", "--env", "Panda-v0", "--seeds", "3", "17", "-n", "2"])
    assert capsys.readouterr().out.splitlines()[-2:] == [
        "Panda-v0: success rate 1.000 over 3 episodes (seeds 10-11 5, absolute actions)",
        "Panda-v0: success rate 1.000 over 2 episodes (seeds 3 17, absolute actions)",
    ]


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--seeds", "5-3"], "argument --seeds: '5-3' is an empty range: FIRST-LAST needs FIRST <= LAST"),
        (["--seeds", "1-x"], "argument --seeds: '1-x' is neither a seed nor a range FIRST-LAST"),
        (["--seeds", "-3"], "argument --seeds: '-3' is neither a seed nor a range FIRST-LAST"),
        (["--seeds", "1-3", "-n", "2"], "-n 2 conflicts with --seeds, which gives 3 episodes (one per seed)"),
        (["--seeds", "1", "--seed", "1"], "argument --seed: not allowed with argument --seeds"),
        (["-n", "0"], "-n needs at least 1 episode, got 0"),
        (["--env", "Nope-v0"], "argument --env: invalid choice: 'Nope-v0'"),
    ],
    ids=["reversed-range", "not-a-range", "negative", "n-and-seeds", "seed-and-seeds", "no-episodes", "unknown-env"],
)
def test_bad_arguments_are_usage_errors(capsys, arguments, message):
    with pytest.raises(SystemExit) as exit_:
        main(["pid", *arguments])
    assert exit_.value.code == 2
    assert error_lines(capsys)[-1].startswith(ERROR + message)


@pytest.mark.parametrize(
    ("model", "algo", "message"),
    [
        ("missing.zip", "bc", "no saved model at {folder}/missing.zip"),
        ("", "bc", "no saved model at {folder} (a folder)"),
        (
            "text.zip",
            "bc",
            "cannot load {folder}/text.zip as a bc model (ValueError: Error: the file {folder}/text.zip wasn't",
        ),
        ("truncated.zip", "cql", "cannot load {folder}/truncated.zip as a cql model"),
        ("bc_delta.zip", "td3", "cannot load {folder}/bc_delta.zip as a td3 model (AttributeError: "),
        ("bc_delta.zip", "nope", "unknown --algo 'nope': one of a2c, "),
        (
            "pendulum.zip",
            "sac",
            "{folder}/pendulum.zip: the model's observation space Box([-1. -1. -8.], [1. 1. 8.], (3,), "
            "float32) is not that of Panda-v0: Box(-inf, inf, (29,), float32)",
        ),
    ],
    ids=["missing", "folder", "text", "truncated", "other-algo", "unknown-algo", "other-task"],
)
def test_a_model_that_cannot_be_evaluated_is_a_one_line_error(models, capsys, model, algo, message):
    folder = models["bc_delta"].parent
    with pytest.raises(SystemExit) as exit_:
        main([str(folder / model) if model else str(folder), "--algo", algo, "--env", "Panda-v0"])
    assert exit_.value.code == 2
    (line,) = error_lines(capsys)
    assert line.startswith(ERROR + message.format(folder=folder))


def test_the_command_reports_a_wrong_action_mode_without_a_traceback(models):
    command = [sys.executable, "-m", "sb3_cql.evaluate", str(models["bc_delta"]), "--algo", "bc", "--env", "Panda-v0",
               "--env-kwargs", "action_mode:'absolute'"]  # fmt: skip
    finished = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert finished.returncode == 2
    lines = [line for line in finished.stderr.splitlines() if not line.startswith("pybullet build time")]  # its banner
    assert len(lines) == 1 and lines[0].startswith(ERROR + str(models["bc_delta"]) + ": the model's action space")
    assert "Traceback" not in finished.stderr and finished.stdout.count("success rate") == 0


def start_command(*args: str) -> subprocess.Popen:
    """``python -m sb3_cql.evaluate ARGS`` as a real process, in a process group of its own (as a shell runs it)."""
    return subprocess.Popen([sys.executable, "-m", "sb3_cql.evaluate", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip


def stderr_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if not line.startswith("pybullet build time")]  # its banner


def test_ctrl_c_while_the_command_starts_is_one_line():
    status, stderr = interrupt_while_starting([sys.executable, "-m", "sb3_cql.evaluate", "pid", "--env", "Panda-v0"])
    assert status == 130
    assert stderr_lines(stderr) == ["python -m sb3_cql.evaluate: interrupted while starting: nothing done"]


@pytest.mark.parametrize(("signum", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_during_an_evaluation_says_in_one_line_what_its_output_holds(tmp_path, signum, status):
    output = tmp_path / "out folder" / "episodes.json"
    process = start_command("pid", "--env", "Panda-v0", "PandaForce-v0", "--seeds", "0-29", "--output", str(output))
    try:
        # A task's line is printed once --output holds it; the second task's 30 episodes are then under way.
        assert any(line.startswith("Panda-v0: success rate") for line in iter(process.stdout.readline, ""))
        os.killpg(process.pid, signum)  # as a terminal's Ctrl-C reaches the whole process group
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == status and "Traceback" not in stderr
    assert stderr_lines(stderr) == [f"interrupted: {output} holds the tasks finished before (Panda-v0)"]
    assert list(json.loads(output.read_text())["tasks"]) == ["Panda-v0"]
