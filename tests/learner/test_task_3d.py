"""The 3d task: elevation geometry at hand-computed points, its reward, its ends in a real World, planar untouched."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from learner_service.inprocess_env import TrackingEnv
from learner_service.registry import LATENT_SCRIPTED, load_policy
from learner_service.scripted import LatentTracker, ScriptedTracker
from learner_service.task import (
    CAUSE_DISTANCE,
    CAUSE_VISIBILITY,
    NO_CAUSE,
    Frame,
    TaskSettings,
    TrackingTask,
    frame_reward,
)
from services.geometry import ALPHA_DEG, BETA_DEG, CAMERA_ABOVE_M, CAMERA_AHEAD_M, OPT_D, vertical_geometry
from services.telemetry import Telemetry
from sim_service.settings import DolphinSettings, WorldSettings
from sim_service.world import World

ZERO = (0.0, 0.0, 0.0)
ROVER = (1.0, -2.0, -4.0)
#: Rewards of seed 23 under seeded random actions, both reward versions, recorded before the 3d task existed
#: (rounded to 1e-9, as tests/sim/test_dolphin.py's digest is).
PLANAR_REWARDS_DIGEST = "8ed5f3df5406fa1fbda4b5af07038523b820578d0ae6f87fbd7bf454f5e2720b"


def quat(yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a yaw about z then a pitch about the body's y; positive pitch is nose up."""
    yaw, pitch = math.radians(yaw_deg) / 2, -math.radians(pitch_deg) / 2  # about +y, positive turns the nose down
    return (
        math.cos(yaw) * math.cos(pitch),
        -math.sin(yaw) * math.sin(pitch),
        math.cos(yaw) * math.sin(pitch),
        math.sin(yaw) * math.cos(pitch),
    )


def telemetry(target: tuple[float, float, float], yaw_deg: float = 0.0, pitch_deg: float = 0.0, **flags) -> Telemetry:
    yaw = math.radians(yaw_deg)
    return Telemetry(
        rover_pos=ROVER,
        rover_quat=quat(yaw_deg, pitch_deg),
        rover_forward=(math.cos(yaw), math.sin(yaw), 0.0),
        rover_lin_vel=ZERO,
        rover_ang_vel=ZERO,
        target_pos=target,
        target_quat=quat(),
        target_forward=(1.0, 0.0, 0.0),
        target_lin_vel=ZERO,
        target_in_frustum=flags.get("in_frustum", True),
        collided=False,
        sim_time=0.0,
    )


def from_camera(ahead: float, left: float, up: float, yaw_deg: float = 0.0) -> tuple[float, float, float]:
    """World position of a point ``ahead``, ``left`` and ``up`` of the camera of a level rover heading ``yaw_deg``."""
    yaw = math.radians(yaw_deg)
    ahead += CAMERA_AHEAD_M
    return (
        ROVER[0] + ahead * math.cos(yaw) - left * math.sin(yaw),
        ROVER[1] + ahead * math.sin(yaw) + left * math.cos(yaw),
        ROVER[2] + CAMERA_ABOVE_M + up,
    )


@pytest.mark.parametrize(
    ("ahead", "left", "up", "yaw_deg", "elevation"),
    [
        (4.0, 0.0, 4.0, 0.0, 45.0),  # 4 m ahead and 4 m above the camera
        (4.0, 0.0, -4.0, 0.0, -45.0),  # below: negative
        (4.0, 0.0, 4.0, 90.0, 45.0),  # the rover's heading does not matter
        (4.0, 0.0, 4.0, -135.0, 45.0),
        (3.0, 4.0, 5.0, 0.0, 45.0),  # 5 m off the axis in the camera's horizontal plane, 5 m up
        (6.0, 0.0, 6.0 * math.sqrt(3.0), 0.0, 60.0),
        (6.0, 0.0, 0.0, 30.0, 0.0),
        (0.0, 0.0, 2.0, 0.0, 90.0),  # straight above the camera
    ],
)
def test_elevation_at_hand_computed_points(ahead, left, up, yaw_deg, elevation) -> None:
    geometry = vertical_geometry(telemetry(from_camera(ahead, left, up, yaw_deg), yaw_deg))
    assert geometry.elevation == pytest.approx(elevation, abs=1e-9)
    assert geometry.phi == pytest.approx(abs(elevation), abs=1e-9)


def test_distance_is_3d_and_from_the_rover_centre() -> None:
    target = (ROVER[0] + 3.0, ROVER[1] + 4.0, ROVER[2] + 12.0)
    assert vertical_geometry(telemetry(target)).distance == pytest.approx(13.0)


def test_a_pitched_rover_measures_elevation_in_its_camera_frame() -> None:
    """Nose up 10 degrees: a point on the camera's axis is at 0; a point level with the camera is 10 below."""
    pitch = math.radians(10.0)
    camera = (ROVER[0] + CAMERA_AHEAD_M * math.cos(pitch) - CAMERA_ABOVE_M * math.sin(pitch), ROVER[1],
              ROVER[2] + CAMERA_AHEAD_M * math.sin(pitch) + CAMERA_ABOVE_M * math.cos(pitch))  # fmt: skip
    on_axis = (camera[0] + 5 * math.cos(pitch), camera[1], camera[2] + 5 * math.sin(pitch))
    level = (camera[0] + 5.0, camera[1], camera[2])
    assert vertical_geometry(telemetry(on_axis, pitch_deg=10.0)).elevation == pytest.approx(0.0, abs=1e-9)
    assert vertical_geometry(telemetry(level, pitch_deg=10.0)).elevation == pytest.approx(-10.0, abs=1e-9)


@pytest.mark.parametrize(
    ("phi", "expected"),
    [
        (0.0, 1.0),  # at opt_d, dead ahead, level: the best step
        (BETA_DEG, 0.0),  # at the edge of the view vertically: the elevation term takes all
        (80.0, 0.0),  # capped at beta, like the azimuth term at alpha
        (5.0, 1.0 - math.log1p(5.0) / math.log1p(BETA_DEG)),
    ],
)
def test_swimm2_3d_reward_at_hand_computed_points(phi: float, expected: float) -> None:
    info = {"d": OPT_D, "theta": 0.0, "phi": phi}
    assert frame_reward(info, "swimm2") == pytest.approx(expected, abs=1e-12)


def test_swimm1_3d_reward_adds_a_linear_elevation_term() -> None:
    assert frame_reward({"d": OPT_D + 2.0, "theta": 18.0, "phi": 45.0}, "swimm1") == pytest.approx(
        1.0 - (4.0 / 16.0 + 0.1 + 0.5)
    )


def test_3d_reward_is_at_most_one_and_one_only_on_target() -> None:
    grid = [
        frame_reward({"d": d, "theta": theta, "phi": phi}, version)
        for version in ("swimm2", "swimm1")
        for d in np.linspace(0.0, 15.0, 16)
        for theta in np.linspace(0.0, 180.0, 13)
        for phi in np.linspace(0.0, 90.0, 10)
    ]
    assert max(grid) == 1.0
    assert min(grid[: len(grid) // 2]) == -2.0  # swimm2: three capped penalties, the lowest step -2


def test_3d_task_steps_on_3d_distance_and_elevation() -> None:
    task = TrackingTask(TaskSettings(obs="state", task="3d"))
    task.reset(Frame(telemetry(from_camera(6.0, 0.0, 0.0))))
    above = telemetry(from_camera(4.0, 0.0, 4.0))
    _, reward, terminated, info = task.step((0.0, 0.0, 0.0), Frame(above))
    geometry = vertical_geometry(above)
    assert info["d"] == geometry.distance and info["elevation"] == pytest.approx(45.0)
    assert reward == frame_reward({"d": geometry.distance, "theta": info["theta"], "phi": 45.0}, "swimm2")
    assert not terminated
    far_above = telemetry((ROVER[0] + 6.0, ROVER[1], ROVER[2] + 9.0))  # 6 m away level, 10.8 m in 3d
    _, _, terminated, info = task.step((0.0, 0.0, 0.0), Frame(far_above))
    assert terminated and info["cause"] == CAUSE_DISTANCE


def test_an_unknown_task_is_refused_naming_it() -> None:
    with pytest.raises(ValueError, match=r"unknown task 'spherical'; choose planar, 3d"):
        TaskSettings(task="spherical")  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def world_3d():
    world = World(WorldSettings(dolphin=DolphinSettings(motion="3d")))
    world.reset(5)
    yield world
    world.close()


@pytest.fixture(scope="module")
def dolphin_pixels(world_3d):
    """How many of the nose camera's 64 x 64 pixels show the dolphin now: MuJoCo's segmentation rendering."""
    return lambda: int(world_3d.target_mask().sum())


@pytest.mark.parametrize(
    ("elevation", "cause"),
    [(20.0, NO_CAUSE), (-20.0, NO_CAUSE), (50.0, CAUSE_VISIBILITY), (-50.0, CAUSE_VISIBILITY)],
)
def test_the_episode_ends_when_the_dolphin_leaves_the_view_vertically(world_3d, dolphin_pixels, elevation, cause):
    """Dead ahead, 3 m from the camera horizontally, crossing the view: above or below the frustum ends it, and
    the rendered frame agrees: it shows the dolphin exactly when the episode goes on."""
    up = 3.0 * math.tan(math.radians(elevation))
    telemetry, _ = world_3d.place(np.array(ROVER), 0.0, np.array(from_camera(3.0, 0.0, up)), math.pi / 2)
    task = TrackingTask(TaskSettings(obs="state", task="3d"))
    task.reset(Frame(telemetry))
    telemetry, _ = world_3d.step((0.0, 0.0, 0.0, 0.0))
    _, _, terminated, info = task.step((0.0, 0.0, 0.0), Frame(telemetry))
    assert info["theta"] < 1.0 < ALPHA_DEG  # horizontally the dolphin is dead ahead
    assert info["elevation"] == pytest.approx(elevation, abs=1.0)
    assert (info["cause"], terminated) == (cause, cause != NO_CAUSE)
    assert (dolphin_pixels() > 0) == (cause == NO_CAUSE)


def test_the_3d_task_in_process_tracks_the_3d_dolphin() -> None:
    env = TrackingEnv(TaskSettings(obs="state", task="3d"))
    assert env.world.settings.dolphin.motion == "3d" and not env.world.settings.render
    _, info = env.reset(seed=3)
    assert {"elevation", "phi"} <= info.keys()
    env.close()
    assert TrackingEnv(TaskSettings(obs="state")).world.settings.dolphin.motion == "planar"


def test_the_3d_task_acts_in_surge_heave_yaw_and_planar_in_surge_yaw() -> None:
    planar, task_3d = TrackingEnv(TaskSettings(obs="state")), TrackingEnv(TaskSettings(obs="state", task="3d"))
    assert planar.action_space.shape == (2,) and task_3d.action_space.shape == (3,)
    assert planar.observation_space.shape == (12 + 10 * 2,) and task_3d.observation_space.shape == (12 + 10 * 3,)
    assert task_3d.task.to_sim_action((0.5, -0.25, 2.0)) == (0.0, -0.25, 0.5, 1.0)  # (sway, heave, surge, yaw)
    task_3d.reset(seed=3)
    with pytest.raises(ValueError, match=r"3d task's policy action must be \(surge, heave, yaw\), got shape \(2,\)"):
        task_3d.step((0.0, 0.0))
    planar.close()
    task_3d.close()


def test_heave_moves_the_depth_setpoint_and_centred_heave_holds_depth() -> None:
    """Full heave climbs at the depth hold's climb rate, as ArduSub's ALT_HOLD stick does; centred, depth holds."""
    env = TrackingEnv(TaskSettings(obs="state", task="3d", early_termination=False))
    _, info = env.reset(seed=3)
    rover, start = env.world.rover, info["telemetry"].rover_pos[2]

    def depths(heave: float, steps: int) -> np.ndarray:
        return np.array([env.step((0.0, heave, 0.0))[4]["telemetry"].rover_pos[2] for _ in range(steps)])

    assert np.abs(depths(0.0, 300) - start).max() < 0.05 and rover.depth_setpoint == start
    climbing = 200
    climbed = depths(1.0, climbing)
    setpoint = rover.depth_setpoint
    assert setpoint - start == pytest.approx(climbing * env.world.dt * rover.gains.max_climb_rate)
    assert climbed[-1] > start + 0.5 * (setpoint - start)  # the rover follows it up
    held = depths(0.0, 1000)  # the depth controller's overshoot settles within 20 s
    assert rover.depth_setpoint == setpoint and held[-1] == pytest.approx(setpoint, abs=0.02)
    env.close()


def test_the_tracker_s_heave_law_keeps_a_diving_dolphin_in_view_vertically() -> None:
    """Seed 11's dolphin dives 3.4 m below the rover's start: with heave 0 its centre leaves the vertical field of
    view (phi past beta); climbing and diving toward its elevation keeps it near the middle of the frame."""

    def episode(heave: bool) -> tuple[float, float]:
        env = TrackingEnv(TaskSettings(obs="state", task="3d", early_termination=False, max_steps=1500))
        tracker, obs, info = ScriptedTracker(), *env.reset(seed=11)
        phis, done = [], False
        while not done:
            action = tracker.act(obs, info) * (1.0, float(heave), 1.0)
            obs, _, _, done, info = env.step(action)
            phis.append(info["phi"])
        env.close()
        return float(np.mean(np.minimum(phis, BETA_DEG)) / BETA_DEG), max(phis)  # E, and the worst elevation error

    followed, held = episode(heave=True), episode(heave=False)
    assert followed[0] < 0.15 and followed[1] < BETA_DEG / 3
    assert held[0] > 0.5 and held[1] > BETA_DEG


def test_the_camera_only_tracker_holds_depth_on_a_planar_cmvae() -> None:
    """The shipped CMVAE reads no elevation: heave 0, whatever the ground truth's elevation."""
    tracker = load_policy(LATENT_SCRIPTED, None)  # the shipped CMVAE's decoders
    latent_obs = np.zeros(10 + 10 * 3, np.float32)
    surge, heave, yaw = tracker.act(latent_obs, {"elevation": 20.0})
    assert heave == 0.0 and (surge, yaw) == tuple(tracker.act(latent_obs[:30], {}))


@pytest.mark.parametrize(
    ("read_elevation", "heave"),
    [(5.0, 0.5), (-20.0, -1.0), (0.5, 0.0)],  # heave_gain 0.1 per degree; a full dive; the 1-degree dead band
)
def test_the_camera_only_tracker_heaves_on_the_elevation_a_vertical_cmvae_reads(read_elevation, heave) -> None:
    """Its heave follows the decoded elevation, not the ground truth's (``info`` only says the task is 3d)."""

    def decode(latents: np.ndarray) -> tuple[np.ndarray, ...]:
        return tuple(np.array([value], np.float32) for value in (OPT_D, 0.0, 0.0, read_elevation))

    tracker = LatentTracker(decode, n_z=10)
    _, commanded, _ = tracker.act(np.zeros(10 + 10 * 3, np.float32), {"elevation": 30.0})
    assert commanded == pytest.approx(heave)


def test_planar_rewards_are_the_ones_recorded_before_the_3d_task() -> None:
    rewards = []
    for version in ("swimm2", "swimm1"):
        env = TrackingEnv(TaskSettings(obs="state", reward=version, early_termination=False))
        _, info = env.reset(seed=23)
        assert "phi" not in info
        for action in np.random.default_rng(23).uniform(-1, 1, size=(1500, 2)):
            rewards.append(env.step(action)[1])
        env.close()
    assert hashlib.sha256(np.round(np.array(rewards), 9).tobytes()).hexdigest() == PLANAR_REWARDS_DIGEST
