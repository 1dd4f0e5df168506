"""The dolphin's swim: the planar motion as it always was, and the 3d motion's depth band, pitch and breaths."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from services.settings import SettingsError, load
from sim_service.dive_profile import plot
from sim_service.dolphin import DolphinParams
from sim_service.settings import DolphinSettings, WorldSettings
from sim_service.world import World

STEPS_PER_S = 50
PARAMS = DolphinParams()
#: The planar swim's target telemetry for seeds 3, 17 and 29 under seeded random actions, recorded before the 3d
#: motion was added (rounded to 1e-9, so only a change of the swim, not of the last bit of libm, moves it).
PLANAR_DIGEST = "16134951e6e8873c90cd6847768e840a345d5871cbf76ae617fab9e8e79c9d7d"


@pytest.fixture(scope="module")
def world_3d():
    world = World(WorldSettings(render=False, dolphin=DolphinSettings(motion="3d")))
    yield world
    world.close()


def swim(world: World, seed: int, steps: int) -> np.ndarray:
    """Rows of target position, quaternion, forward and velocity from the reset on, the rover holding still."""
    telemetry, _ = world.reset(seed)
    poses = [telemetry] + [world.step((0, 0, 0, 0))[0] for _ in range(steps)]
    return np.array([[*t.target_pos, *t.target_quat, *t.target_forward, *t.target_lin_vel] for t in poses])


def test_planar_swim_is_the_one_recorded_before_the_3d_motion():
    world = World(WorldSettings(render=False))
    digest = hashlib.sha256()
    for seed in (3, 17, 29):
        actions = np.random.default_rng(seed).uniform(-1, 1, size=(1500, 4))
        poses = [world.reset(seed)[0]] + [world.step(tuple(action))[0] for action in actions]
        fields = [[*t.target_pos, *t.target_quat, *t.target_forward, *t.target_lin_vel] for t in poses]
        digest.update(np.round(np.array(fields), 9).tobytes())
    world.close()
    assert digest.hexdigest() == PLANAR_DIGEST


def test_3d_swim_replays_from_its_seed_and_another_seed_swims_elsewhere(world_3d):
    other = World(WorldSettings(render=False, dolphin=DolphinSettings(motion="3d")))
    first = swim(world_3d, 5, 3000)
    assert np.array_equal(first, swim(other, 5, 3000))
    other.close()
    assert not np.array_equal(first[1:], swim(world_3d, 6, 3000)[1:])
    assert np.ptp(first[:, 2]) > 1.0  # it does change depth


def test_3d_swim_stays_in_its_depth_band_pitching_and_climbing_within_the_limits(world_3d):
    poses = swim(world_3d, 7, 20_000)
    z, forward, velocity = poses[:, 2], poses[:, 7:10], poses[:, 10:13]
    assert PARAMS.floor_z <= z.min() and z.max() <= PARAMS.ceiling_z
    climb = np.degrees(np.arcsin(forward[:, 2]))
    assert np.abs(climb).max() <= PARAMS.max_climb_deg + 1e-9
    assert climb.min() < -30 and climb.max() > 30  # it dives and climbs steeply, not only drifts
    assert np.abs(np.diff(climb)).max() <= PARAMS.max_climb_rate_deg_per_step + 1e-9
    vertical_speed = np.diff(z) * STEPS_PER_S
    assert np.abs(vertical_speed).max() <= PARAMS.speed_range[1] * math.sin(math.radians(PARAMS.max_climb_deg)) + 1e-9
    inside = (z[1:] > PARAMS.floor_z) & (z[1:] < PARAMS.ceiling_z)  # away from the band's edges, where it is held
    np.testing.assert_allclose(vertical_speed[inside], velocity[1:, 2][inside], atol=1e-9)


def test_3d_body_pitches_nose_up_in_a_climb(world_3d):
    poses = swim(world_3d, 7, 3000)
    quat, forward = poses[:, 3:7], poses[:, 7:10]
    w, x, y, z = quat.T
    nose_up = np.degrees(np.arcsin(2 * (x * z - w * y)))  # the body's x axis' world z, from the quaternion
    climb = np.degrees(np.arcsin(forward[:, 2]))
    assert np.abs(nose_up - climb).max() <= PARAMS.body_pitch_deg + 1e-6  # the climb, give or take the undulation


@pytest.mark.parametrize("seed", range(4))
def test_3d_dolphin_surfaces_within_150_s_and_again_later(world_3d, seed):
    """The first breath comes within the longest interval (100 s) and the climb from the floor (< 50 s)."""
    z = swim(world_3d, seed, 400 * STEPS_PER_S)[:, 2]
    at_surface = np.flatnonzero(z >= PARAMS.ceiling_z)
    assert at_surface.size and at_surface[0] <= 150 * STEPS_PER_S
    breaths = 1 + np.count_nonzero(np.diff(at_surface) > STEPS_PER_S)
    assert breaths >= 3  # over 400 s


def test_the_motion_is_a_world_setting_and_a_bad_one_is_refused_by_name(tmp_path):
    config = tmp_path / "world.yaml"
    config.write_text("dolphin:\n  motion: 3d\n")
    assert load(WorldSettings, config_file=config).dolphin.motion == "3d"
    assert load(WorldSettings).dolphin.motion == "planar"
    with pytest.raises(SettingsError, match="'spiral'"):
        load(WorldSettings, environ={"SWIMM_DOLPHIN_MOTION": "spiral"})
    with pytest.raises(ValueError, match="unknown dolphin motion 'spiral'; choose one of planar, 3d"):
        World(WorldSettings(render=False, dolphin=DolphinSettings(motion="spiral")))


def test_the_dive_profile_figure_is_drawn(tmp_path):
    out = plot(seed=7, seconds=2.0, out=tmp_path / "profile.png")
    assert out.stat().st_size > 0
