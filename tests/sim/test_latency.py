"""Camera and control delays in the world: each one against an undelayed world driven by hand to the same effect."""

from __future__ import annotations

import os

import numpy as np
import pytest

from sim_service.latency import NEUTRAL, LatencyLine, LatencySettings
from sim_service.settings import WorldSettings
from sim_service.world import World

os.environ.setdefault("MUJOCO_GL", "egl")
SEED = 2024
STEPS = 24


def actions(count: int = STEPS) -> list[tuple[float, ...]]:
    """A varied command sequence (sway, heave, surge, yaw) that moves the rover and turns it."""
    rng = np.random.default_rng(5)
    return [(0.0, 0.0, float(surge), float(yaw)) for surge, yaw in rng.uniform(-1, 1, (count, 2))]


def play(latency: LatencySettings, commands: list[tuple[float, ...]], seed: int = SEED):
    world = World(WorldSettings(latency=latency))
    try:
        telemetry, frame = world.reset(seed)
        poses, frames = [telemetry.rover_pos], [frame]
        for action in commands:
            telemetry, frame = world.step(action)
            poses.append(telemetry.rover_pos)
            frames.append(frame)
        return np.array(poses), np.stack(frames), world.latency.settings
    finally:
        world.close()


@pytest.fixture(scope="module")
def undelayed():
    return play(LatencySettings(), actions())


def test_an_observation_delay_shows_frames_k_steps_old_and_leaves_the_physics_alone(undelayed) -> None:
    poses, frames, _ = undelayed
    delayed_poses, delayed_frames, _ = play(LatencySettings(observation_delay=3), actions())
    np.testing.assert_array_equal(delayed_poses, poses)  # ground truth (the reward's) stays current
    np.testing.assert_array_equal(delayed_frames[3:], frames[:-3])
    for step in range(3):  # the episode's first frame stands in for the ones before it
        np.testing.assert_array_equal(delayed_frames[step], frames[0])


def test_an_action_delay_applies_each_action_m_steps_after_it_arrived(undelayed) -> None:
    delayed_poses, _, _ = play(LatencySettings(action_delay=4), actions())
    by_hand, _, _ = play(LatencySettings(), [NEUTRAL] * 4 + actions()[:-4])
    np.testing.assert_array_equal(delayed_poses, by_hand)
    assert not np.array_equal(delayed_poses, undelayed[0])


def test_a_control_period_holds_each_action_for_n_steps() -> None:
    commands = actions()
    held = [commands[step - step % 3] for step in range(STEPS)]
    np.testing.assert_array_equal(
        play(LatencySettings(control_period=3), commands)[0], play(LatencySettings(), held)[0]
    )


def test_randomised_latency_is_drawn_within_its_ranges_from_the_seed_without_changing_the_episode(undelayed) -> None:
    ranges = LatencySettings(observation_delay=8, action_delay=5, control_period=5, randomise=True)
    drawn = [play(ranges, [], seed)[2] for seed in range(12)]
    assert all(0 <= d.observation_delay <= 8 and 0 <= d.action_delay <= 5 and 1 <= d.control_period <= 5 for d in drawn)
    assert len({(d.observation_delay, d.action_delay, d.control_period) for d in drawn}) > 6
    assert all(not d.randomise for d in drawn)
    assert play(ranges, [], 7)[2] == drawn[7]  # the same seed, the same draw
    first_pose, first_frame = play(ranges, [])[0][0], play(ranges, [])[1][0]
    np.testing.assert_array_equal(first_pose, undelayed[0][0])  # the reset's own draws are untouched
    np.testing.assert_array_equal(first_frame, undelayed[1][0])


@pytest.mark.parametrize(
    "settings",
    [LatencySettings(observation_delay=-1), LatencySettings(action_delay=-2), LatencySettings(control_period=0)],
)
def test_impossible_delays_are_refused_by_name(settings: LatencySettings) -> None:
    with pytest.raises(ValueError, match="latency: observation_delay and action_delay must be >= 0"):
        World(WorldSettings(render=False, latency=settings))
    with pytest.raises(ValueError, match="control_period >= 1"):
        LatencyLine(settings, None)
