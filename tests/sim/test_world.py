"""Physics, camera and determinism of the MuJoCo world, with the numbers the SPEC and the BlueROV2 give."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from services.geometry import ALPHA_DEG, HFOV_DEG, VFOV_DEG, relative_geometry, yaw_of
from services.messages import DiveMode
from sim_service.noise import NoiseSettings
from sim_service.rotations import euler_to_matrix
from sim_service.settings import WorldSettings
from sim_service.world import TARGET_BOX, World

STEPS_PER_S = 50


@pytest.fixture(scope="module")
def physics_world():
    world = World(WorldSettings(render=False))
    yield world
    world.close()


@pytest.fixture(scope="module")
def camera_world():
    world = World()
    yield world
    world.close()


def run(world: World, action, steps: int, mode=DiveMode.DEPTH_HOLD):
    telemetry = None
    for _ in range(steps):
        telemetry, _ = world.step(action, mode)
    return telemetry


def test_depth_holds_within_3cm_for_60s_with_zero_command(physics_world):
    start, _ = physics_world.reset(5)
    worst = 0.0
    for _ in range(60 * STEPS_PER_S):
        telemetry, _ = physics_world.step((0, 0, 0, 0))
        worst = max(worst, abs(telemetry.rover_pos[2] - start.rover_pos[2]))
    assert worst < 0.03


def test_without_depth_hold_the_trimmed_rover_floats_up(physics_world):
    start, _ = physics_world.reset(5)
    end = run(physics_world, (0, 0, 0, 0), 10 * STEPS_PER_S, DiveMode.MANUAL)
    assert end.rover_pos[2] - start.rover_pos[2] > 0.1  # 2 N of net buoyancy


def test_full_surge_reaches_bluerov2_top_speed(physics_world):
    physics_world.reset(5)
    end = run(physics_world, (0, 0, 1, 0), 20 * STEPS_PER_S)
    speed = float(np.linalg.norm(end.rover_lin_vel[:2]))
    assert 1.0 <= speed <= 1.6
    forward_speed = float(np.dot(end.rover_lin_vel, end.rover_forward))
    assert forward_speed == pytest.approx(speed, rel=0.01)  # straight ahead, no sway or yaw


def test_the_pose_answering_an_action_has_moved_by_the_velocity_it_reports(physics_world):
    """Semi-implicit Euler: each step moves the rover by its new velocity times dt. A pose one step behind
    (what a bare ``mj_step`` leaves in the position fields) would move by the previous step's velocity."""
    previous, _ = physics_world.reset(5)
    for _ in range(10):
        telemetry, _ = physics_world.step((0, 0, 1, 0))
        moved = (np.array(telemetry.rover_pos) - previous.rover_pos) / physics_world.dt
        assert moved == pytest.approx(telemetry.rover_lin_vel, abs=1e-9)
        assert np.linalg.norm(telemetry.rover_lin_vel) > np.linalg.norm(previous.rover_lin_vel) + 0.01  # speeding up
        previous = telemetry


def test_the_frame_answering_an_action_already_shows_it(camera_world):
    def first_step(action):
        camera_world.reset(3)
        return camera_world.step(action)

    (ahead, ahead_image), (astern, astern_image) = first_step((0, 0, 1, 1)), first_step((0, 0, -1, -1))
    assert ahead.rover_pos != astern.rover_pos
    assert np.abs(ahead_image.astype(int) - astern_image).sum() > 1000


def test_full_yaw_turns_faster_than_the_dolphin_can(physics_world):
    physics_world.reset(5)
    end = run(physics_world, (0, 0, 0, 1), 10 * STEPS_PER_S)
    rate = math.degrees(end.rover_ang_vel[2])
    assert 65.0 < rate < 200.0  # positive yaw turns the nose left (counter-clockwise)


def test_dolphin_speed_and_turn_rate_stay_in_range(physics_world):
    physics_world.reset(11)
    yaws, speeds = [], []
    for _ in range(60 * STEPS_PER_S):
        telemetry, _ = physics_world.step((0, 0, 0, 0))
        yaws.append(math.radians(yaw_of(telemetry.target_forward)))
        speeds.append(float(np.linalg.norm(telemetry.target_lin_vel)))
    turn_rates = np.degrees(np.abs(np.diff(np.unwrap(yaws)))) * STEPS_PER_S
    assert turn_rates.max() <= 65.0 + 1e-6  # 1.3 deg per 0.02 s step
    assert turn_rates.max() > 10.0  # it does turn toward its waypoints
    assert 0.5 <= min(speeds) and max(speeds) <= 1.0


def test_reset_draws_follow_the_spec(physics_world):
    for seed in range(40):
        telemetry, _ = physics_world.reset(seed)
        geometry = relative_geometry(telemetry)
        assert 4.0 <= geometry.d <= 8.0
        assert geometry.theta <= ALPHA_DEG + 1e-9
        assert abs(telemetry.rover_pos[0]) <= 30 and abs(telemetry.rover_pos[1]) <= 30
        assert telemetry.rover_pos[2] == pytest.approx(-4.0)
        assert telemetry.target_in_frustum


def _pinhole_sees_some_point(telemetry, camera_pos, camera_rot, samples=9) -> bool:
    """Independent check: project a dense grid of the target's box with the SPEC's field of view."""
    axes = euler_to_matrix(0, 0, math.atan2(telemetry.target_forward[1], telemetry.target_forward[0]))
    half = np.array(TARGET_BOX) / 2
    grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, samples)] * 3), -1).reshape(-1, 3) * half
    points = np.array(telemetry.target_pos) + grid @ axes.T
    local = (points - camera_pos) @ camera_rot
    depth = -local[:, 2]
    ok = depth > 0.05
    x = local[ok, 0] / (depth[ok] * math.tan(math.radians(HFOV_DEG / 2)))
    y = local[ok, 1] / (depth[ok] * math.tan(math.radians(VFOV_DEG / 2)))
    return bool(np.any((np.abs(x) <= 1) & (np.abs(y) <= 1)))


def test_in_frustum_flag_agrees_with_pinhole_projection(physics_world):
    world = physics_world
    rng = np.random.default_rng(0)
    agree = checked = 0
    for _ in range(300):
        azimuth = math.radians(rng.uniform(-90, 90))
        distance = rng.uniform(2, 12)
        target = np.array([distance * math.cos(azimuth), distance * math.sin(azimuth), -4 + rng.uniform(-3, 3)])
        telemetry, _ = world.place(np.array([0, 0, -4.0]), 0.0, target, rng.uniform(-math.pi, math.pi))
        camera = world.model.camera("nose").id
        seen = _pinhole_sees_some_point(
            telemetry, world.data.cam_xpos[camera], world.data.cam_xmat[camera].reshape(3, 3)
        )
        checked += 1
        agree += seen == telemetry.target_in_frustum
        if seen:  # a visible sample point proves the box overlaps the frustum
            assert telemetry.target_in_frustum
    assert agree / checked > 0.97  # the rest are boxes grazing an edge between sample points


def test_flag_is_false_when_the_target_is_behind(physics_world):
    telemetry, _ = physics_world.place(np.array([0, 0, -4.0]), 0.0, np.array([-6.0, 0, -4.0]), 0.0)
    assert not telemetry.target_in_frustum


def test_collision_is_reported_when_bodies_touch(physics_world):
    apart, _ = physics_world.place(np.array([0, 0, -4.0]), 0.0, np.array([3.0, 0, -4.0]), math.pi / 2)
    assert not apart.collided
    touching, _ = physics_world.place(np.array([0, 0, -4.0]), 0.0, np.array([0.5, 0, -4.0]), math.pi / 2)
    telemetry, _ = physics_world.step((0, 0, 0, 0))
    assert telemetry.collided and not apart.collided and touching.target_pos[0] == 0.5


def test_same_seed_and_actions_give_identical_bytes(camera_world):
    rng = np.random.default_rng(3)
    actions = [tuple(rng.uniform(-1, 1, 4)) for _ in range(50)]

    def episode():
        frames = [camera_world.reset(42)]
        frames += [camera_world.step(a) for a in actions]
        return [(t, img.tobytes()) for t, img in frames]

    assert episode() == episode()
    other, _ = camera_world.reset(43)
    assert other != episode()[0][0]


def test_preparing_steps_ahead_changes_no_byte(camera_world):
    """What the served sim does while it waits for an action (prepare_step, once or twice) leaves every
    telemetry field and pixel as stepping alone gives them, across an episode boundary too."""
    rng = np.random.default_rng(4)
    actions = [tuple(rng.uniform(-1, 1, 4)) for _ in range(40)]

    def episodes(prepare_times: int):
        frames = []
        for seed in (42, 43):
            for _ in range(prepare_times):
                camera_world.prepare_step()  # thrown away by the reset
            frames.append(camera_world.reset(seed))
            for action in actions:
                for _ in range(prepare_times):
                    camera_world.prepare_step()
                frames.append(camera_world.step(action))
        return [(t, img.tobytes()) for t, img in frames]

    assert episodes(1) == episodes(0) == episodes(2)


def test_a_prepared_step_thrown_away_gives_its_random_draws_back(physics_world):
    def place_after(prepare: bool):
        physics_world.reset(9)
        physics_world.step((0, 0, 0, 0))
        # Put the waypoint under the dolphin: its next swim step arrives there and draws a new one.
        physics_world.dolphin.state.waypoint = physics_world.dolphin.state.position[:2].copy()
        before = physics_world.rng.bit_generator.state
        if prepare:
            physics_world.prepare_step()
            assert physics_world.rng.bit_generator.state != before  # the swim drew a waypoint
        placed = physics_world.place(np.array([0, 0, -4.0]), 0.0, np.array([5.0, 0, -4.0]), 1.0)[0]
        return placed, physics_world.step((0, 0, 0, 0))[0], physics_world.rng.bit_generator.state

    assert place_after(prepare=True) == place_after(prepare=False)


def test_dolphin_is_visible_across_the_reset_ranges(camera_world):
    """Pixel statistics: the frame with the dolphin differs from the same frame with it moved away."""
    far = np.array([0.0, 0.0, 500.0])
    for seed in range(20):
        telemetry, image = camera_world.reset(seed)
        rover = np.array(telemetry.rover_pos)
        _, empty = camera_world.place(rover, math.radians(yaw_of(telemetry.rover_forward)), rover + far, 0.0)
        changed = np.abs(image.astype(int) - empty.astype(int)).sum(axis=2) > 12
        assert changed.sum() >= 6, f"seed {seed}: dolphin covers only {changed.sum()} px"


def test_frames_look_underwater(camera_world):
    _, image = camera_world.reset(1)
    mean = image.reshape(-1, 3).mean(axis=0)
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert mean[2] > mean[0] and mean[1] > mean[0]  # blue-green water, red absorbed


def test_render_scale_downsamples_to_the_image_size():
    world = World(WorldSettings(render_scale=2))
    try:
        _, image = world.reset(1)
        assert image.shape == (64, 64, 3)
    finally:
        world.close()


def test_render_threads_change_speed_not_pixels(camera_world):
    """Frames drawn by llvmpipe's worker threads (Mesa's default) equal those drawn on the stepping thread.

    Mesa reads the thread count once per process, so the threaded frame comes from a child process.
    """
    script = (
        "import sys; from sim_service.settings import WorldSettings; from sim_service.world import World; "
        "w = World(WorldSettings(render_threads=-1)); w.reset(4); "
        "sys.stdout.buffer.write(w.step((0, 0, 1, 1))[1].tobytes())"
    )
    environment = {**os.environ, "LP_NUM_THREADS": "2"}
    threaded = subprocess.run([sys.executable, "-c", script], capture_output=True, check=True, env=environment).stdout
    camera_world.reset(4)
    _, image = camera_world.step((0.0, 0.0, 1.0, 1.0))
    assert os.environ["LP_NUM_THREADS"] == "0"
    assert threaded == image.tobytes()


# --- image noise ---------------------------------------------------------------------------------


def _episode(world: World, seed: int, noise: bool | None, steps: int = 20):
    telemetry, image = world.reset(seed, noise=noise)
    frames, poses = [image], [telemetry]
    for _ in range(steps):
        telemetry, image = world.step((0.0, 0.0, 0.6, 0.8))  # turning: motion blur has something to smear
        frames.append(image)
        poses.append(telemetry)
    return poses, np.stack(frames)


def test_noise_changes_frames_but_never_the_trajectory_and_replays_exactly(camera_world):
    clean_poses, clean = _episode(camera_world, 21, noise=False)
    noisy_poses, noisy = _episode(camera_world, 21, noise=True)
    again_poses, again = _episode(camera_world, 21, noise=True)
    assert noisy_poses == clean_poses  # noise draws from its own stream
    assert np.array_equal(noisy, again)  # and that stream is the seed's
    difference = np.abs(noisy.astype(int) - clean.astype(int)).mean(axis=(1, 2, 3))
    assert np.all(difference > 3.0)  # every frame degraded, by more than a rounding error
    assert _high_frequency(noisy[0]) > 1.5 * _high_frequency(clean[0])  # the film grain is there


def _high_frequency(image: np.ndarray) -> float:
    return float((image.astype(float) - cv2.GaussianBlur(image, (5, 5), 0).astype(float)).std())


def test_noise_choice_persists_until_the_next_reset_says_otherwise(camera_world):
    _, noisy = _episode(camera_world, 22, noise=True, steps=0)
    _, kept = _episode(camera_world, 22, noise=None, steps=0)
    _, clean = _episode(camera_world, 22, noise=False, steps=0)
    _, fresh = _episode(World(), 22, noise=None, steps=0)  # a new world starts from its settings: clean
    assert np.array_equal(kept, noisy)
    assert np.array_equal(clean, fresh) and not np.array_equal(clean, noisy)


def test_configured_noise_is_on_from_the_start(camera_world):
    settings = WorldSettings(noise=NoiseSettings(fog=0.3))
    world = World(settings)
    _, image = world.reset(23)
    world.close()
    _, clean = camera_world.reset(23, noise=False)
    water = np.array(settings.noise.fog_color, float)
    # Fog pulls every pixel toward the water colour: the foggy frame is closer to it than the clean one.
    assert np.abs(image - water).mean() < 0.8 * np.abs(clean - water).mean()


def test_randomised_noise_is_drawn_per_episode_from_its_seed_and_never_moves_the_trajectory(camera_world):
    from sim_service.noise import EFFECTS, PRESETS

    maxima = NoiseSettings(preset="harsh", randomise=True)
    world = World(WorldSettings(noise=maxima))
    try:
        first_poses, first = _episode(world, 31, noise=None, steps=5)
        first_noise = world.noise_settings
        _, other = _episode(world, 32, noise=None, steps=5)
        other_noise = world.noise_settings
        again_poses, again = _episode(world, 31, noise=None, steps=5)
        assert world.noise_settings == first_noise and np.array_equal(again, first)  # the seed fixes the draw
        assert first_noise != other_noise and not np.array_equal(first, other)
        for name in EFFECTS:  # inside the preset's range
            drawn, top = getattr(first_noise, name), getattr(PRESETS["harsh"], name)
            assert (top <= drawn <= 100) if name == "jpeg_quality" else (0 <= drawn <= top)
        clean_poses, clean = _episode(camera_world, 31, noise=False, steps=5)
        assert first_poses == clean_poses and not np.array_equal(first, clean)
        assert np.array_equal(world.clean_frame, clean[-1])  # the frame before noise is the clean world's
    finally:
        world.close()
