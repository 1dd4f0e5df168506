"""TrackingTask: rewards and terminations at hand-computed points, ActPrev, observation spaces, seeding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from learner_service.task import (
    Frame,
    TaskSettings,
    TrackingTask,
    episode_seed,
    swimm1_reward,
    swimm2_reward,
    violation_cause,
)
from services.geometry import ALPHA_DEG
from services.telemetry import Telemetry

ZERO = (0.0, 0.0, 0.0)


def yaw_quat(yaw_deg: float) -> tuple[float, float, float, float]:
    half = math.radians(yaw_deg) / 2
    return (math.cos(half), 0.0, 0.0, math.sin(half))


def telemetry_at(
    d: float,
    azimuth_deg: float,
    rover_pos: tuple[float, float, float] = (0.0, 0.0, -4.0),
    rover_yaw_deg: float = 0.0,
    target_yaw_deg: float = 0.0,
    in_frustum: bool = True,
    collided: bool = False,
) -> Telemetry:
    """A rover at ``rover_pos`` heading ``rover_yaw_deg`` and a target at distance d and signed azimuth."""
    bearing = math.radians(rover_yaw_deg + azimuth_deg)
    rover_yaw = math.radians(rover_yaw_deg)
    target_yaw = math.radians(target_yaw_deg)
    target = (rover_pos[0] + d * math.cos(bearing), rover_pos[1] + d * math.sin(bearing), rover_pos[2])
    return Telemetry(
        rover_pos=rover_pos,
        rover_quat=yaw_quat(rover_yaw_deg),
        rover_forward=(math.cos(rover_yaw), math.sin(rover_yaw), 0.0),
        rover_lin_vel=ZERO,
        rover_ang_vel=ZERO,
        target_pos=target,
        target_quat=yaw_quat(target_yaw_deg),
        target_forward=(math.cos(target_yaw), math.sin(target_yaw), 0.0),
        target_lin_vel=ZERO,
        target_in_frustum=in_frustum,
        collided=collided,
        sim_time=0.0,
    )


def latent_frame(d: float = 6.0, azimuth: float = 0.0, mu: float = 0.5, **kwargs) -> Frame:
    return Frame(telemetry_at(d, azimuth, **kwargs), mu=np.full(10, mu, np.float32), logvar=np.zeros(10, np.float32))


# --- rewards -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("d", "theta", "expected"),
    [
        (6.0, 0.0, 1.0),  # on target: no penalty
        (7.0, 0.0, 0.967941396719915),  # 1 - (e - 1) / (e^4 - 1)
        (5.0, 0.0, 0.967941396719915),  # symmetric in d - opt_d
        (6.0, 10.0, 0.35418659887173787),  # 1 - ln(11) / ln(1 + alpha)
        (8.0, 20.0, 0.060830746411240866),  # 1 - (e^2 - 1)/(e^4 - 1) - ln(21)/ln(1 + alpha)
        (10.0, 0.0, 0.0),  # distance penalty at its cap
        (6.0, ALPHA_DEG, 0.0),  # azimuth penalty at its cap
        (2.0, ALPHA_DEG, -1.0),  # both at their caps: the floor
        (15.0, 120.0, -1.0),  # beyond the caps the penalties stay at 1
    ],
)
def test_swimm2_reward_at_hand_computed_points(d: float, theta: float, expected: float) -> None:
    assert swimm2_reward(d, theta) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize(
    ("d", "theta", "expected"),
    [
        (6.0, 0.0, 1.0),
        (8.0, 45.0, 0.5),  # 1 - (4/16 + 45/180)
        (4.0, 90.0, 0.25),  # 1 - (4/16 + 90/180)
        (14.0, 180.0, -4.0),  # 1 - (64/16 + 1): uncapped
    ],
)
def test_swimm1_reward_at_hand_computed_points(d: float, theta: float, expected: float) -> None:
    assert swimm1_reward(d, theta) == pytest.approx(expected, abs=1e-12)


def test_step_reward_uses_the_chosen_version_and_the_frame_geometry() -> None:
    for version, expected in (("swimm2", 0.060830746411240866), ("swimm1", 1 - (4 / 16 + 20 / 180))):
        task = TrackingTask(TaskSettings(reward=version))
        task.reset(latent_frame())
        _, reward, _, info = task.step((0.0, 0.0), latent_frame(d=8.0, azimuth=-20.0))
        assert reward == pytest.approx(expected, abs=1e-9)
        assert info["d"] == pytest.approx(8.0)
        assert info["theta"] == pytest.approx(20.0)
        assert info["azimuth"] == pytest.approx(-20.0)


# --- termination ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frame_kwargs", "cause"),
    [
        ({"d": 9.99}, ""),
        ({"d": 10.0}, "distance"),  # |d - opt_d| >= max_d
        ({"d": 2.0}, "distance"),
        ({"d": 1.5}, "distance"),
        ({"d": 6.0, "in_frustum": False}, "visibility"),
        ({"d": 6.0, "collided": True}, "collision"),
        ({"d": 10.5, "in_frustum": False, "collided": True}, "collision"),  # most severe first
        ({"d": 10.5, "in_frustum": False}, "visibility"),
    ],
)
def test_termination_causes(frame_kwargs: dict, cause: str) -> None:
    task = TrackingTask(TaskSettings(obs="cmvae"))
    task.reset(latent_frame())
    _, _, terminated, info = task.step((0.0, 0.0), latent_frame(**frame_kwargs))
    assert info["cause"] == cause
    assert terminated is (cause != "")


def test_without_early_termination_the_cause_is_reported_but_the_episode_goes_on() -> None:
    task = TrackingTask(TaskSettings(early_termination=False))
    task.reset(latent_frame())
    _, _, terminated, info = task.step((0.0, 0.0), latent_frame(d=11.0, collided=True))
    assert info["cause"] == "collision"
    assert terminated is False
    assert violation_cause(11.0, True, False) == "distance"


def test_time_up_after_max_steps() -> None:
    task = TrackingTask(TaskSettings(max_steps=3))
    task.reset(latent_frame())
    flags = []
    for _ in range(3):
        task.step((0.0, 0.0), latent_frame())
        flags.append(task.time_up)
    assert flags == [False, False, True]
    task.reset(latent_frame())
    assert task.elapsed_steps == 0 and not task.time_up


# --- actions and ActPrev -------------------------------------------------------------------------


def test_to_sim_action_holds_sway_and_heave_and_clips() -> None:
    task = TrackingTask()
    assert task.to_sim_action((0.25, -0.75)) == (0.0, 0.0, 0.25, -0.75)
    assert task.to_sim_action(np.array([2.0, -3.0])) == (0.0, 0.0, 1.0, -1.0)
    with pytest.raises(ValueError, match="finite"):
        task.to_sim_action((math.nan, 0.0))
    with pytest.raises(ValueError, match=r"planar task's policy action must be \(surge, yaw\)"):
        task.to_sim_action((0.1, 0.2, 0.3))


def test_action_history_is_zero_padded_and_oldest_first() -> None:
    task = TrackingTask(TaskSettings(obs="cmvae", n_prev_actions=10))
    obs = task.reset(latent_frame(mu=0.5))
    assert obs.shape == (30,)
    np.testing.assert_array_equal(obs[:10], np.full(10, 0.5, np.float32))
    np.testing.assert_array_equal(obs[10:], np.zeros(20, np.float32))

    obs, *_ = task.step((0.1, -0.2), latent_frame())
    np.testing.assert_allclose(obs[10:], [0.0] * 18 + [0.1, -0.2], atol=1e-7)
    obs, *_ = task.step((0.3, 0.4), latent_frame())
    np.testing.assert_allclose(obs[10:], [0.0] * 16 + [0.1, -0.2, 0.3, 0.4], atol=1e-7)

    actions = [(k / 20, -k / 20) for k in range(3, 12)]  # 9 more: 11 actions taken in all, the first drops out
    for action in actions:
        obs, *_ = task.step(action, latent_frame())
    expected = np.array([(0.3, 0.4), *actions], np.float32).reshape(-1)
    np.testing.assert_allclose(obs[10:], expected, atol=1e-7)

    obs = task.reset(latent_frame())
    np.testing.assert_array_equal(obs[10:], np.zeros(20, np.float32))


def test_history_holds_the_clipped_action() -> None:
    task = TrackingTask(TaskSettings(n_prev_actions=2))
    task.reset(latent_frame())
    obs, *_ = task.step((5.0, -5.0), latent_frame())
    np.testing.assert_array_equal(obs[10:], [0.0, 0.0, 1.0, -1.0])


# --- observations --------------------------------------------------------------------------------


def test_cmvae_observation_space() -> None:
    task = TrackingTask(TaskSettings(obs="cmvae"))
    assert task.observation_space.shape == (30,)
    assert task.action_space.shape == (2,)
    assert task.action_space.low.tolist() == [-1.0, -1.0] and task.action_space.high.tolist() == [1.0, 1.0]
    obs = task.reset(latent_frame(mu=-123.0))
    assert task.observation_space.contains(obs)
    obs, *_ = task.step((1.0, -1.0), latent_frame(mu=7.0))
    assert task.observation_space.contains(obs)


def test_image_observation_space() -> None:
    task = TrackingTask(TaskSettings(obs="image"))
    image = np.arange(64 * 64 * 3, dtype=np.int64).reshape(64, 64, 3).astype(np.uint8)
    frame = Frame(telemetry_at(6.0, 0.0), image=image)
    obs = task.reset(frame)
    assert set(obs) == {"image", "actions"}
    assert obs["image"].shape == (64, 64, 3) and obs["image"].dtype == np.uint8
    assert obs["actions"].shape == (20,)
    assert task.observation_space.contains(obs)
    obs, *_ = task.step((0.5, 0.5), frame)
    assert task.observation_space.contains(obs)
    np.testing.assert_array_equal(obs["actions"][-2:], [0.5, 0.5])


def test_state_observation_holds_positions_and_euler_angles() -> None:
    task = TrackingTask(TaskSettings(obs="state"))
    telemetry = telemetry_at(5.0, 0.0, rover_pos=(1.0, 2.0, -4.0), rover_yaw_deg=90.0, target_yaw_deg=-45.0)
    obs = task.reset(Frame(telemetry))
    assert obs.shape == (32,)
    assert task.observation_space.contains(obs)
    # rover faces +y, so the target (azimuth 0, 5 m ahead) sits at (1, 7, -4)
    expected_head = [1.0, 2.0, -4.0, 0.0, 0.0, math.pi / 2, 1.0, 7.0, -4.0, 0.0, 0.0, -math.pi / 4]
    np.testing.assert_allclose(obs[:12], expected_head, atol=1e-6)
    np.testing.assert_array_equal(obs[12:], np.zeros(20))


def test_missing_inputs_are_refused_clearly() -> None:
    with pytest.raises(ValueError, match="needs frames with the encoder's mu"):
        TrackingTask(TaskSettings(obs="cmvae")).reset(Frame(telemetry_at(6.0, 0.0)))
    with pytest.raises(ValueError, match="needs frames with an image"):
        TrackingTask(TaskSettings(obs="image")).reset(Frame(telemetry_at(6.0, 0.0)))
    with pytest.raises(ValueError, match="10 values"):
        TrackingTask().reset(Frame(telemetry_at(6.0, 0.0), mu=np.zeros(8)))
    with pytest.raises(ValueError, match="logvar"):
        TrackingTask(TaskSettings(use_latent_mean=False)).reset(Frame(telemetry_at(6.0, 0.0), mu=np.zeros(10)))
    with pytest.raises(ValueError, match="unknown observation mode"):
        TaskSettings(obs="pixels")  # type: ignore[arg-type]


def test_sampled_latents_follow_mu_and_logvar_and_the_episode_seed() -> None:
    task = TrackingTask(TaskSettings(use_latent_mean=False, n_prev_actions=0))
    frame = Frame(telemetry_at(6.0, 0.0), mu=np.full(10, 1.0), logvar=np.full(10, math.log(4.0)))  # std 2
    first = task.reset(frame, seed=11)
    samples = np.array([task.step((0.0, 0.0), frame)[0] for _ in range(4000)])
    assert samples.mean() == pytest.approx(1.0, abs=0.05)
    assert samples.std() == pytest.approx(2.0, abs=0.05)
    assert np.array_equal(task.reset(frame, seed=11), first)  # same episode seed, same draw
    assert not np.array_equal(task.reset(frame, seed=12), first)
    mean_task = TrackingTask(TaskSettings(use_latent_mean=True, n_prev_actions=0))
    np.testing.assert_array_equal(mean_task.reset(frame, seed=11), np.ones(10))


# --- seeds ---------------------------------------------------------------------------------------


def test_episode_seeds_are_deterministic_distinct_and_32_bit() -> None:
    assert episode_seed(97, 1) == episode_seed(97, 1)
    seeds = {episode_seed(base, ep) for base in (97, 101, 103, 107, 109) for ep in range(1, 401)}
    assert len(seeds) == 5 * 400
    assert all(0 <= seed < 2**32 for seed in seeds)
    assert episode_seed(97, 5) != episode_seed(101, 1)  # not base + ep
    with pytest.raises(ValueError):
        episode_seed(-1, 1)
