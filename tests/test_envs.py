"""Behaviour of the three grasping tasks."""

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import envs
from envs.task import TRAY_FLOOR_HEIGHT, TRAY_POSITION

ACTION_MODES = ["absolute", "delta"]


def rollout(env: gym.Env, actions: np.ndarray, seed: int) -> np.ndarray:
    observations = [env.reset(seed=seed)[0]]
    for action in actions:
        observations.append(env.step(action)[0])
    return np.stack(observations)


@pytest.mark.parametrize("action_mode", ACTION_MODES)
def test_random_rollout_stays_in_spaces(env_id, action_mode, make_env):
    env = make_env(env_id, action_mode=action_mode)
    env.action_space.seed(0)
    observation, info = env.reset(seed=0)
    assert observation.shape == (29,) and observation.dtype == np.float32
    assert info["is_success"] is False
    for _ in range(100):
        observation, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(observation)
        assert np.all(np.isfinite(observation))
        assert reward == float(info["is_success"])
        assert terminated == info["is_success"] and not truncated


@pytest.mark.parametrize("action_mode", ACTION_MODES)
def test_gymnasium_and_sb3_env_checkers_pass(env_id, action_mode, make_env):
    gymnasium_check_env(make_env(env_id, action_mode=action_mode).unwrapped, skip_render_check=True)
    sb3_check_env(make_env(env_id, action_mode=action_mode).unwrapped, warn=False)


def test_same_seed_and_actions_give_identical_observations(env_id, make_env):
    env, other = make_env(env_id), make_env(env_id)
    actions = np.random.default_rng(1).uniform(env.action_space.low, env.action_space.high, size=(40, 9))
    first = rollout(env, actions, seed=7)
    rollout(env, actions[::-1], seed=8)  # an episode in between must not leak into the next one
    np.testing.assert_array_equal(rollout(env, actions, seed=7), first)
    np.testing.assert_array_equal(rollout(other, actions, seed=7), first)
    assert not np.array_equal(rollout(other, actions, seed=9)[0], first[0])


def test_reset_with_seed_then_without_is_deterministic(env_id, make_env):
    env, other = make_env(env_id), make_env(env_id)
    env.reset(seed=3)
    other.reset(seed=3)
    first, info = env.reset()
    second, other_info = other.reset()
    np.testing.assert_array_equal(first, second)
    assert info == other_info


def test_render_returns_rgb_frame(env_id, make_env):
    env = make_env(env_id, render_mode="rgb_array", render_width=64, render_height=48)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
    assert frame.std() > 0


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
def test_non_finite_action_raises(bad_value, make_env):
    env = make_env("Panda-v0")
    env.reset(seed=0)
    action = np.zeros(9)
    action[3] = bad_value
    with pytest.raises(ValueError, match="finite"):
        env.step(action)


def test_wrong_action_shape_raises(make_env):
    env = make_env("Panda-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(7))


@pytest.mark.parametrize("action_mode", ACTION_MODES)
def test_out_of_bounds_actions_are_clipped(action_mode, make_env):
    env = make_env("Panda-v0", action_mode=action_mode)
    robot = env.unwrapped.robot  # the float64 limits the float32 action space rounds
    low, high = (robot.lower_limits, robot.upper_limits) if action_mode == "absolute" else (-1.0, 1.0)
    beyond = np.where(np.arange(9) % 2 == 0, high + 5.0, low - 5.0)
    at_bounds = np.where(np.arange(9) % 2 == 0, high, low)
    np.testing.assert_array_equal(rollout(env, [beyond] * 5, seed=0), rollout(env, [at_bounds] * 5, seed=0))


def test_action_space_is_joint_limits_or_unit_box(make_env):
    absolute = make_env("Panda-v0").action_space
    assert absolute.shape == (9,)
    assert absolute.low[3] == pytest.approx(-3.1416) and absolute.high[3] == 0.0
    assert absolute.low[7] == 0.0 and absolute.high[7] == pytest.approx(0.04)
    delta = make_env("Panda-v0", action_mode="delta").action_space
    assert np.all(delta.low == -1.0) and np.all(delta.high == 1.0)


def test_zero_delta_action_holds_the_arm(make_env):
    env = make_env("Panda-v0", action_mode="delta")
    observations = rollout(env, [np.zeros(9)] * 20, seed=0)
    np.testing.assert_allclose(observations[-1, :9], observations[0, :9], atol=1e-3)


def test_physics_keywords_reach_the_simulation(make_env):
    env = make_env("Panda-v0", object_mass=0.5, object_lateral_friction=0.3, gravity=-9.81)
    _, info = env.reset(seed=0)
    assert info["object_mass"] == 0.5 and info["gravity"] == -9.81
    unwrapped = env.unwrapped
    dynamics = unwrapped.sim.client.getDynamicsInfo(unwrapped.task.object, -1)
    assert dynamics[0] == pytest.approx(0.5) and dynamics[1] == pytest.approx(0.3)


def test_unknown_keyword_raises_type_error():
    with pytest.raises(TypeError, match="object_colour"):
        gym.make("Panda-v0", object_colour="red")


def test_unknown_action_mode_raises():
    with pytest.raises(ValueError, match="action_mode"):
        gym.make("Panda-v0", action_mode="velocity")


def test_perturbed_env_samples_physics_from_its_ranges(make_env):
    env = make_env("PandaPerturbed-v0")
    config = env.unwrapped.config
    samples = [env.reset(seed=seed)[1] for seed in range(20)]
    for key, (low, high) in [
        ("gravity", config.gravity_range),
        ("object_mass", config.object_mass_range),
        ("object_lateral_friction", config.object_friction_range),
    ]:
        values = np.array([info[key] for info in samples])
        assert np.all((values >= low) & (values <= high))
        assert values.std() > 0.1 * (high - low)
    standard = make_env("Panda-v0").reset(seed=0)[1]
    assert (standard["gravity"], standard["object_mass"], standard["object_lateral_friction"]) == (-10.0, 0.1, 0.1)


def test_object_starts_resting_in_the_tray(env_id, make_env):
    env = make_env(env_id)
    config = env.unwrapped.config
    for seed in range(5):
        observation, _ = env.reset(seed=seed)
        x, y, z = observation[envs.OBSERVATION_SLICES["object_position"]]
        assert config.object_x_range[0] <= x <= config.object_x_range[1]
        assert config.object_y_range[0] <= y <= config.object_y_range[1]
        assert z == pytest.approx(TRAY_FLOOR_HEIGHT + config.object_height / 2, abs=0.005)


def test_flung_object_is_not_a_success(make_env):
    env = make_env("Panda-v0", action_mode="delta")
    env.reset(seed=0)
    unwrapped = env.unwrapped
    unwrapped.sim.client.resetBasePositionAndOrientation(unwrapped.task.object, [0.6, 0.0, 0.6], [0, 0, 0, 1])
    observation, reward, terminated, _, info = env.step(np.zeros(9))
    assert observation[18] > 0.4
    assert reward == 0.0 and not terminated and not info["is_success"]


def test_episode_is_truncated_at_700_steps(make_env):
    env = make_env("Panda-v0", action_mode="delta")
    env.reset(seed=0)
    for step in range(1, 701):
        _, _, terminated, truncated, _ = env.step(np.zeros(9))
        assert not terminated
        assert truncated == (step == 700)


def run_pd(env: gym.Env, controller: envs.PDController, seed: int) -> tuple[bool, list[dict]]:
    observation, _ = env.reset(seed=seed)
    infos, done = [], False
    while not done:
        action, _ = controller.predict(observation)
        observation, _, terminated, truncated, info = env.step(action)
        infos.append(info)
        done = terminated or truncated
    return infos[-1]["is_success"], infos


@pytest.mark.parametrize("regrasp", [False, True])
@pytest.mark.parametrize("action_mode", ACTION_MODES)
def test_pd_controller_solves_panda(action_mode, regrasp, make_env):
    env = make_env("Panda-v0", action_mode=action_mode)
    controller = envs.PDController.for_env(env, regrasp=regrasp)
    results = [run_pd(env, controller, seed) for seed in range(4)]
    assert all(success for success, _ in results)
    assert all(len(infos) < 300 for _, infos in results)


def test_pd_controller_commands_the_gripper_fully_open_or_closed_in_delta_mode(make_env):
    env = make_env("Panda-v0", action_mode="delta")
    controller = envs.PDController.for_env(env)
    observation, _ = env.reset(seed=0)
    finger_actions = set()
    for _ in range(300):
        action, _ = controller.predict(observation)
        finger_actions.update(action[-2:].tolist())
        observation, _, terminated, _, _ = env.step(action)
        if terminated:
            break
    assert finger_actions == {-1.0, 1.0}


def test_force_knocks_the_object_out_once(make_env):
    env = make_env("PandaForce-v0")
    controller = envs.PDController.for_env(env)
    success, infos = run_pd(env, controller, seed=0)
    assert sum(info["force_applied"] for info in infos) == 1
    assert not success


@pytest.mark.parametrize("action_mode", ACTION_MODES)
def test_regrasping_pd_controller_picks_the_knocked_out_object_up_again(action_mode, make_env):
    env = make_env("PandaForce-v0", action_mode=action_mode)
    # The episode the plain controller fails (test_force_knocks_the_object_out_once).
    success, infos = run_pd(env, envs.PDController.for_env(env, regrasp=True), seed=0)
    assert sum(info["force_applied"] for info in infos) == 1
    assert success


def test_pd_controller_works_with_sb3_evaluate_policy():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    vec_env = make_vec_env("Panda-v0", n_envs=2, seed=0)
    controller = envs.PDController()
    actions, _ = controller.predict(vec_env.reset())
    assert actions.shape == (2, 9) and actions.dtype == np.float32
    mean_reward, _ = evaluate_policy(controller, vec_env, n_eval_episodes=2)
    assert mean_reward == 1.0
    vec_env.close()


def test_pd_controller_does_not_disturb_the_env(make_env):
    env = make_env("Panda-v0")
    observation, _ = env.reset(seed=0)
    unwrapped = env.unwrapped
    before = unwrapped.sim.client.getJointStates(unwrapped.robot.body, list(range(12)))
    envs.PDController.for_env(env).predict(observation)
    assert unwrapped.sim.client.getJointStates(unwrapped.robot.body, list(range(12))) == before


def run_stateful(env: gym.Env, controller: envs.PDController, seed: int) -> dict[str, np.ndarray]:
    """One episode reset with ``seed``, the controller seeded with it and its state passed along, SB3-style: each
    step's observation, action, attempt yaw and dropped flag, and whether it succeeded."""
    controller.seed(seed)
    observation, _ = env.reset(seed=seed)
    steps = {"observations": [], "actions": [], "yaws": [], "dropped": []}
    state, done, info = None, False, {}
    while not done:
        action, state = controller.predict(observation, state, np.array([not steps["actions"]]))
        attempt = (0.0, False) if state is None else (state[0][0], state[1][0])  # the fixed yaw keeps no state
        for key, value in zip(steps, (observation, action, *attempt), strict=True):
            steps[key].append(value)
        observation, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return {**{key: np.array(value) for key, value in steps.items()}, "success": info["is_success"]}


def closing_steps(actions: np.ndarray, action_mode: str) -> np.ndarray:
    """The steps at which the controller starts closing the gripper (its finger action turns from open to closed)."""
    closed = actions[:, -1] < 0 if action_mode == "delta" else actions[:, -1] == 0
    return np.flatnonzero(closed[1:] & ~closed[:-1]) + 1


def object_axis(observation: np.ndarray) -> np.ndarray:
    return envs.pd_controller._axis(observation[envs.OBSERVATION_SLICES["object_orientation"]].astype(np.float64), 2)


def closing_angle(observation: np.ndarray) -> float:
    """The angle (degrees, 0 to 90) between the horizontal line through the two fingers and the object's axis."""
    fingers = observation[envs.OBSERVATION_SLICES["finger_offsets"]]
    across, axis = (fingers[:3] - fingers[3:])[:2], object_axis(observation)[:2]
    cosine = abs(across @ axis) / (np.linalg.norm(across) * np.linalg.norm(axis))
    return float(np.degrees(np.arccos(min(cosine, 1.0))))


def test_random_yaw_is_uniform_over_a_half_turn_at_each_episode_start(make_env):
    env = make_env("Panda-v0")
    observation, _ = env.reset(seed=0)
    controller = envs.PDController.for_env(env, **envs.CONTROLLERS["pid-regrasp-yaw"], seed=0)
    _, (yaws, dropped) = controller.predict(np.tile(observation, (1000, 1)))  # no state: each an episode's start
    half = envs.pd_controller.YAW_HALF_RANGE
    assert half == pytest.approx(np.pi / 2) and not dropped.any()
    assert yaws.min() >= -half and yaws.max() < half
    counts, _ = np.histogram(yaws, bins=5, range=(-half, half))
    assert np.all(np.abs(counts - 200) < 50), counts  # 4 standard deviations of a uniform draw's bin count


def test_random_yaw_is_held_through_an_attempt_and_redrawn_at_a_regrasp(make_env):
    env = make_env("PandaForce-v0")
    controller = envs.PDController.for_env(env, **envs.CONTROLLERS["pid-regrasp-yaw"])
    episode = run_stateful(env, controller, seed=0)
    yaws, dropped = episode["yaws"], episode["dropped"]
    attempts = np.concatenate([[0], np.flatnonzero(dropped[1:] & ~dropped[:-1]) + 1])
    assert len(attempts) >= 2  # the knock-out made it regrasp
    changes = np.flatnonzero(np.diff(yaws)) + 1
    np.testing.assert_array_equal(changes, attempts[1:])  # a new yaw at each new attempt and at no other step
    assert len(set(yaws[attempts].tolist())) == len(attempts)
    # It turns while hovering: at each closing the hand has the attempt's yaw.
    hand_yaws = [envs.pd_controller.hand_yaw(o[envs.OBSERVATION_SLICES["ee_orientation"]]) for o in episode["observations"]]
    for step in closing_steps(episode["actions"], "absolute"):
        assert abs(hand_yaws[step] - yaws[step]) < envs.pd_controller.YAW_TOLERANCE


def test_random_yaw_is_seeded(make_env):
    env = make_env("PandaForce-v0", action_mode="delta")
    controller = envs.PDController.for_env(env, **envs.CONTROLLERS["pid-regrasp-yaw"])
    first, again = (run_stateful(env, controller, seed=3) for _ in range(2))
    np.testing.assert_array_equal(first["actions"], again["actions"])
    np.testing.assert_array_equal(first["yaws"], again["yaws"])
    other = envs.PDController.for_env(env, **envs.CONTROLLERS["pid-regrasp-yaw"], seed=4)
    observation, _ = env.reset(seed=3)
    assert other.predict(observation)[1][0][0] != first["yaws"][0]  # another seed, another yaw of the same episode
    # A generator is drawn from as it is; a seed gives a stream apart from the env's (whose pose draws it would repeat).
    other.seed(np.random.default_rng(3))
    assert other.predict(observation)[1][0][0] == pytest.approx(np.random.default_rng(3).uniform(-np.pi / 2, np.pi / 2))
    controller.seed(3)
    assert controller.predict(observation)[1][0][0] != pytest.approx(np.random.default_rng(3).uniform(-np.pi / 2, np.pi / 2))


def test_episode_start_resets_the_attempt(make_env):
    env = make_env("Panda-v0")
    observation, _ = env.reset(seed=0)
    controller = envs.PDController.for_env(env, **envs.CONTROLLERS["pid-regrasp-yaw"], seed=0)
    last_episode = (np.array([0.3]), np.array([True]))  # the previous episode ended in a drop, at yaw 0.3
    _, (kept, dropped) = controller.predict(observation, last_episode, np.array([False]))
    assert kept[0] == 0.3 and not dropped[0]  # the same episode: an open hand above the object is no new attempt
    controller.seed(0)
    first_draw = controller.predict(observation)[1][0][0]
    controller.seed(0)
    _, (yaw, dropped) = controller.predict(observation, last_episode, np.array([True]))
    assert yaw[0] == first_draw != 0.3 and not dropped[0]
    with pytest.raises(ValueError, match="yaw must be one of"):
        envs.PDController(yaw="sideways")


@pytest.mark.parametrize("action_mode", ACTION_MODES)
def test_random_yaw_controller_solves_panda(action_mode, make_env):
    env = make_env("Panda-v0", action_mode=action_mode)
    controller = envs.PDController.for_env(env, **envs.CONTROLLERS["pid-regrasp-yaw"])
    episodes = [run_stateful(env, controller, seed) for seed in range(3)]
    assert all(episode["success"] for episode in episodes)
    assert len({episode["yaws"][0] for episode in episodes}) == 3 and max(abs(e["yaws"][0]) for e in episodes) > 0.3


def test_aligned_controller_closes_across_a_lying_cylinder(make_env):
    env = make_env("PandaForce-v0")
    lying = np.cos(envs.pd_controller.LYING_TILT)
    angles = {}
    for name in ("pid-regrasp-aligned", "pid-regrasp"):
        episode = run_stateful(env, envs.PDController.for_env(env, **envs.CONTROLLERS[name]), seed=0)
        steps = [step for step in closing_steps(episode["actions"], "absolute")
                 if abs(object_axis(episode["observations"][step])[2]) < lying]  # fmt: skip
        assert steps, f"{name} never closed on the knocked-out cylinder lying on its side"
        angles[name] = closing_angle(episode["observations"][steps[0]])
    assert angles["pid-regrasp-aligned"] > 80  # the fingers close across the axis
    assert angles["pid-regrasp"] < 30  # with the fixed yaw they closed along it, in this episode


def test_closing_angles_measure_the_fingers_against_a_lying_cylinders_axis(make_env):
    env = make_env("PandaForce-v0")
    measured = {}
    for name in ("pid-regrasp-aligned", "pid-regrasp"):
        episode = run_stateful(env, envs.PDController.for_env(env, **envs.CONTROLLERS[name]), seed=0)
        angles = envs.pd_controller.closing_angles(episode["observations"])
        closings = closing_steps(episode["actions"], "absolute")
        # One angle per closing of the open hand on the object (the fingers move a step after the action), None
        # for the upright cylinder of the first grasp, the angle of the line through the fingers for a lying one.
        assert len(angles) == len(closings) >= 2 and angles[0] is None
        steps = envs.pd_controller.closing_steps(episode["observations"])
        assert np.abs(steps - np.asarray(closings)).max() <= 5  # the width passes 5 mm less within a few steps
        for angle, step in zip(angles[1:], closings[1:], strict=True):
            assert angle == pytest.approx(closing_angle(episode["observations"][step]), abs=3.0)
        measured[name] = angles[1]
    assert measured["pid-regrasp-aligned"] > 80 and measured["pid-regrasp"] < 30
    upright = np.zeros(29)
    upright[envs.OBSERVATION_SLICES["object_orientation"]] = [0.0, 0.0, 0.0, 1.0]
    upright[envs.OBSERVATION_SLICES["ee_orientation"]] = envs.pd_controller.HAND_ORIENTATION
    assert envs.pd_controller.closing_angle(upright) is None
    lying = upright.copy()  # the cylinder's axis along the world y axis, the fingers' closing direction
    lying[envs.OBSERVATION_SLICES["object_orientation"]] = [np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)]
    assert envs.pd_controller.closing_angle(lying) == pytest.approx(0.0, abs=1e-6)
    lying[envs.OBSERVATION_SLICES["ee_orientation"]] = envs.pd_controller.hand_orientation(np.pi / 3)
    assert envs.pd_controller.closing_angle(lying) == pytest.approx(60.0)


def test_reference_controllers_are_named_controllers():
    assert set(envs.pd_controller.REFERENCE_CONTROLLERS) <= set(envs.CONTROLLERS)
    assert envs.pd_controller.aligned_yaw(np.array([0.0, 0.0, 0.0, 1.0])) == 0.0  # upright: the fixed yaw
    along_y = np.array([np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])  # lying along the world y axis (x rotation)
    assert abs(envs.pd_controller.aligned_yaw(along_y)) == pytest.approx(np.pi / 2)


def clearance(position: np.ndarray, radius: float) -> float:
    """Height of the object's centre above what it can rest on (the tray floor or the ground), minus the
    cylinder's radius: >= 0 for an object at rest, negative while it is pressed into that surface."""
    x, y, z = position
    in_tray = abs(x - TRAY_POSITION[0]) < 0.3 and abs(y - TRAY_POSITION[1]) < 0.3
    return z - (TRAY_FLOOR_HEIGHT if in_tray else 0.0) - radius


@pytest.mark.slow
@pytest.mark.parametrize("n_episodes", [1000])
def test_random_episodes_have_no_nan_or_tunnelling(env_id, n_episodes, make_env):
    """Random joint targets for 700 steps: never NaN, and the object ends every episode on a surface, never
    inside or beneath the tray floor. The 100 N m arm can crush the 0.1 kg object into the floor or the ground
    for a few steps (a light body pinned by a strong motor is beyond Bullet's iterative solver); that must
    stay rare."""
    env = make_env(env_id)
    env.action_space.seed(0)
    radius = env.unwrapped.config.object_radius
    pressed_in, deepest_of_all = [], 0.0
    for episode in range(n_episodes):
        observation, _ = env.reset(seed=episode)
        deepest, done = 0.0, False
        while not done:
            observation, _, terminated, truncated, _ = env.step(env.action_space.sample())
            assert np.all(np.isfinite(observation)), f"NaN in episode {episode}"
            position = observation[envs.OBSERVATION_SLICES["object_position"]]
            deepest = min(deepest, clearance(position, radius))
            done = terminated or truncated
        assert clearance(position, radius) > -radius / 2, f"object left inside a surface in episode {episode}: {position}"
        if deepest < -radius / 2:
            pressed_in.append(episode)
        deepest_of_all = min(deepest, deepest_of_all)
    print(f"{env_id}: pressed over {radius / 2} m into a surface in episodes {pressed_in}; {-deepest_of_all:.3f} m at most")
    assert len(pressed_in) <= n_episodes // 100


def test_pd_example_saves_a_video(tmp_path):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[1] / "examples" / "pd_controller.py"
    spec = importlib.util.spec_from_file_location("pd_controller_example", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    successes = example.evaluate_pd_controller("Panda-v0", n_episodes=1, seed=0, video_folder=str(tmp_path))
    assert successes == [True]
    videos = list(tmp_path.glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 10_000


MAKE_AND_RESET = "import gymnasium as gym, envs; e = gym.make('Panda-v0'); e.reset(seed=0); print('ok')"


def pybullet_noise(output: str) -> list[str]:
    return [line for line in output.splitlines() if "pybullet build time" in line or "argv[0]=" in line]


def test_pybullet_prints_nothing_when_imported_and_connected(tmp_path):
    result = subprocess.run([sys.executable, "-c", MAKE_AND_RESET], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout == "ok\n"  # through a pipe
    assert pybullet_noise(result.stderr) == []

    # Into files, with output before PyBullet's start-up: kept, in order.
    code = "import sys; print('before'); sys.stderr.write('before\\n'); " + MAKE_AND_RESET
    with open(tmp_path / "out", "w") as out, open(tmp_path / "err", "w") as err:
        subprocess.run([sys.executable, "-c", code], stdout=out, stderr=err, check=True, timeout=120)
    assert (tmp_path / "out").read_text() == "before\nok\n"
    errors = (tmp_path / "err").read_text()
    assert errors.startswith("before\n") and pybullet_noise(errors) == []
