"""The in-process TrackingEnv on the real MuJoCo world, and the scripted tracker's signs and closed loop there."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.monitor import Monitor

from encoder_service.inference import DEFAULT_CHECKPOINT, LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint
from learner_service.envs import make_vec_env
from learner_service.inprocess_env import TrackingEnv
from learner_service.learn_settings import TrackerGains
from learner_service.registry import make_model
from learner_service.scripted import ScriptedTracker
from learner_service.task import TaskSettings, TrackingTask, episode_seed
from services.geometry import ALPHA_DEG, yaw_of
from sim_service.latency import LatencySettings
from sim_service.settings import WorldSettings
from sim_service.world import World

BASE_SEED = 97


@pytest.fixture(scope="module")
def physics_world() -> World:
    world = World(WorldSettings(render=False))
    yield world
    world.close()


def placed_info(world: World, d: float, azimuth_deg: float) -> dict:
    """Rover at the origin facing +x, dolphin at (d, azimuth) swimming along +y; the task's info of that frame."""
    bearing = math.radians(azimuth_deg)
    telemetry, _ = world.place(
        np.array([0.0, 0.0, -4.0]), 0.0, np.array([d * math.cos(bearing), d * math.sin(bearing), -4.0]), math.pi / 2
    )
    return TrackingTask.info(telemetry)


# --- the env -------------------------------------------------------------------------------------


# Positions (and latents) have no natural bound, so the state space's Box is unbounded on purpose.
@pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")
def test_state_env_passes_gymnasium_checks() -> None:
    env = TrackingEnv(TaskSettings(obs="state"), base_seed=BASE_SEED)
    check_env(env, skip_render_check=True)
    env.close()


def test_episodes_count_up_from_one_with_their_seeds() -> None:
    env = TrackingEnv(TaskSettings(obs="state"), base_seed=BASE_SEED)
    seen = []
    for _ in range(3):
        obs, info = env.reset()
        assert env.observation_space.contains(obs)
        assert 4.0 <= info["d"] <= 8.0 and info["theta"] <= ALPHA_DEG  # the SPEC's reset distribution
        assert info["cause"] == "" and info["telemetry"].target_in_frustum
        seen.append((info["ep"], info["seed"]))
    assert seen == [(ep, episode_seed(BASE_SEED, ep)) for ep in (1, 2, 3)]
    _, info = env.reset(seed=5)
    assert (info["ep"], info["seed"]) == (1, episode_seed(5, 1))
    env.close()


def test_same_seed_same_trajectory() -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, (60, 2))

    def rollout() -> tuple[np.ndarray, list[float]]:
        env = TrackingEnv(TaskSettings(obs="state", early_termination=False), base_seed=BASE_SEED)
        observations, rewards = [env.reset()[0]], []
        for action in actions:
            obs, reward, *_ = env.step(action)
            observations.append(obs)
            rewards.append(reward)
        env.close()
        return np.array(observations), rewards

    first, second = rollout(), rollout()
    np.testing.assert_array_equal(first[0], second[0])
    assert first[1] == second[1]
    np.testing.assert_array_equal(first[0][-1][-2:], actions[-1].astype(np.float32))  # ActPrev ends with the last


def test_time_limit_is_reported_as_truncated() -> None:
    env = TrackingEnv(TaskSettings(obs="state", max_steps=5, early_termination=False), base_seed=BASE_SEED)
    env.reset()
    flags = [env.step((0.0, 0.0))[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(False, True)]
    env.close()


def test_step_before_reset_and_images_without_rendering_are_refused() -> None:
    env = TrackingEnv(TaskSettings(obs="state"))
    with pytest.raises(RuntimeError, match="reset"):
        env.step((0.0, 0.0))
    env.close()
    with pytest.raises(ValueError, match="needs a rendering world"):
        TrackingEnv(TaskSettings(obs="image"), WorldSettings(render=False))


def test_image_observation_is_the_rendered_frame() -> None:
    env = TrackingEnv(TaskSettings(obs="image"), base_seed=BASE_SEED)
    obs, _ = env.reset()
    reference = World(WorldSettings())
    _, image = reference.reset(episode_seed(BASE_SEED, 1))
    reference.close()
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs["image"], image)
    assert image.std() > 0  # a real frame, not a blank buffer
    np.testing.assert_array_equal(env.render(), image)  # render() gives the frame the observation came from
    obs, *_ = env.step((0.2, -0.1))
    np.testing.assert_allclose(obs["actions"][-2:], [0.2, -0.1], atol=1e-7)
    np.testing.assert_array_equal(env.render(), obs["image"])
    env.close()


def test_cmvae_observation_is_the_encoders_latent_mean(tmp_path) -> None:
    torch.manual_seed(0)
    checkpoint = tmp_path / "cmvae.pt"
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    encoder = LatentEncoder(checkpoint)
    env = TrackingEnv(TaskSettings(obs="cmvae"), base_seed=BASE_SEED, encoder=encoder)
    obs, _ = env.reset()
    reference = World(WorldSettings())
    _, image = reference.reset(episode_seed(BASE_SEED, 1))
    reference.close()
    mu, _ = encoder.encode(image[None])
    assert obs.shape == (30,) and env.observation_space.contains(obs)
    np.testing.assert_allclose(obs[:10], mu[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(obs[10:], np.zeros(20))
    env.close()


def test_cmvae_default_encoder_loads_lazily() -> None:
    env = TrackingEnv(TaskSettings(obs="cmvae"))  # constructing never needs the checkpoint
    if DEFAULT_CHECKPOINT.is_file():
        assert env.reset()[0].shape == (30,)
    else:
        with pytest.raises(FileNotFoundError, match="swimm train-encoder"):
            env.reset()
    env.close()


def test_sac_trains_on_the_env_through_sb3s_monitor() -> None:
    """SB3 reads info["episode"] as Monitor statistics: the env's own info keys must leave it alone."""
    env = Monitor(TrackingEnv(TaskSettings(obs="state", max_steps=50), base_seed=BASE_SEED))
    model = make_model(
        "sac",
        env,
        seed=BASE_SEED,
        overrides={"device": "cpu", "learning_starts": 20, "gradient_steps": 2, "batch_size": 16},
    )
    model.learn(200)
    assert 200 <= model.num_timesteps < 250  # train_freq is one episode: the last one runs to its end
    assert len(model.ep_info_buffer) >= 4  # at most 50 steps each
    assert all(set(episode) >= {"r", "l"} and episode["l"] <= 50 for episode in model.ep_info_buffer)
    env.close()


# --- the scripted tracker ------------------------------------------------------------------------


def test_scripted_signs_on_world_telemetry(physics_world: World) -> None:
    tracker = ScriptedTracker()
    left = placed_info(physics_world, 6.0, 30.0)
    assert left["azimuth"] == pytest.approx(30.0, abs=1e-6)
    surge, yaw = tracker.act(None, left)
    assert yaw == pytest.approx(30.0 / 60.0) and surge == pytest.approx(0.0, abs=1e-6)
    assert tracker.act(None, placed_info(physics_world, 6.0, -12.0))[1] == pytest.approx(-12.0 / 60.0)
    assert tracker.act(None, placed_info(physics_world, 6.5, 0.0))[0] == pytest.approx(0.5)
    assert tracker.act(None, placed_info(physics_world, 9.0, 0.0))[0] == pytest.approx(1.0)  # clipped
    assert tracker.act(None, placed_info(physics_world, 5.5, 0.0))[0] == pytest.approx(-0.5)
    assert tracker.act(None, placed_info(physics_world, 7.0, 180.0))[0] == pytest.approx(-1.0)  # behind: reverse
    assert tracker.act(None, placed_info(physics_world, 7.0, 90.0))[0] == pytest.approx(0.0, abs=1e-6)  # beside


def test_damped_tracker_subtracts_the_mean_yaw_that_actprev_commanded(physics_world: World) -> None:
    info = placed_info(physics_world, 6.0, 30.0)
    history = np.zeros(20, np.float32)
    history[1::2] = np.linspace(0.0, 0.9, 10)  # yaw commands oldest to newest, mean 0.45; surges are ignored
    history[0::2] = 0.7
    obs = np.concatenate([np.full(10, 5.0, np.float32), history])  # a cmvae observation: latent, then ActPrev
    damped = ScriptedTracker(TrackerGains(yaw_gain=1 / 90, yaw_damping=2.0))
    assert damped.act(obs, info)[1] == pytest.approx(30.0 / 90 - 2.0 * 0.45, abs=1e-6)
    assert damped.act({"image": None, "actions": history}, info)[1] == pytest.approx(30.0 / 90 - 0.9, abs=1e-6)
    assert ScriptedTracker().act(obs, info)[1] == pytest.approx(0.5)  # no damping: ActPrev unread
    with pytest.raises(ValueError, match="--scripted-yaw-damping -1.0: must be >= 0"):
        TrackerGains(yaw_damping=-1.0).check()


def episode_return(tracker: ScriptedTracker, latency: LatencySettings) -> float:
    """One episode of 3000 steps from BASE_SEED with the loop delayed as ``latency`` says."""
    env = TrackingEnv(TaskSettings(obs="state", early_termination=False), base_seed=BASE_SEED)
    env.world.configure_latency(latency)
    obs, info = env.reset()
    total, truncated = 0.0, False
    while not truncated:
        obs, reward, _, truncated, info = env.step(tracker.act(obs, info))
        total += reward
    env.close()
    return total


def test_damping_keeps_the_tracker_steady_when_its_actions_arrive_160_ms_late() -> None:
    late = LatencySettings(action_delay=8)
    proportional = episode_return(ScriptedTracker(), late)
    damped = episode_return(ScriptedTracker(TrackerGains(yaw_gain=1 / 90, yaw_damping=1.5)), late)
    assert damped > proportional + 500.0  # the undamped tracker oscillates about the dolphin's bearing


def test_positive_yaw_turns_the_rover_counter_clockwise(physics_world: World) -> None:
    info = placed_info(physics_world, 6.0, 30.0)
    yaw_command = ScriptedTracker().act(None, info)[1]
    telemetry = info["telemetry"]
    for _ in range(50):
        telemetry, _ = physics_world.step((0.0, 0.0, 0.0, float(yaw_command)))
    assert yaw_of(telemetry.rover_forward) > 5.0  # turned left, toward the target, by more than 5 degrees in 1 s


def test_scripted_tracker_keeps_the_dolphin_for_a_whole_episode() -> None:
    env = TrackingEnv(TaskSettings(obs="state"), base_seed=BASE_SEED)
    tracker = ScriptedTracker()
    obs, info = env.reset()
    total, steps, terminated, truncated = 0.0, 0, False, False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(tracker.act(obs, info))
        total += reward
        steps += 1
    assert (steps, terminated, truncated) == (3000, False, True)
    assert total > 2500.0  # the paper's best SAC reached 2.40e3

    env.reset(seed=BASE_SEED)  # the same episode without control: the dolphin swims away
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step((0.0, 0.0))
        steps += 1
    assert terminated and steps < 3000 and info["cause"] in ("visibility", "distance")
    env.close()


def test_in_process_vec_envs_share_one_renderer_and_see_what_envs_of_their_own_see() -> None:
    """make_vec_env's in-process envs draw through the first one's renderer (one GL context), frame for frame as
    envs with a renderer each: interleaved steps, two episodes each, the second restarted on another seed."""
    task = TaskSettings(obs="image", max_steps=30)
    vec_env = make_vec_env("inprocess", task, n_envs=3, base_seed=BASE_SEED)
    own = [TrackingEnv(task, base_seed=BASE_SEED + index) for index in range(3)]
    try:
        worlds = [env.world for env in vec_env.unwrapped.envs]
        assert all(world._renderer is worlds[0]._renderer for world in worlds)
        assert len({id(env.world._renderer) for env in own}) == 3
        actions = np.random.default_rng(3).uniform(-1, 1, (40, 3, 2)).astype(np.float32)
        frames = [vec_env.reset()["image"]]
        expected = [np.stack([env.reset()[0]["image"] for env in own])]
        for step_actions in actions:  # past max_steps: the vec env resets itself, so the own envs do too
            frames.append(vec_env.step(step_actions)[0]["image"])
            row = []
            for env, action in zip(own, step_actions, strict=True):
                obs, _, terminated, truncated, _ = env.step(action)
                row.append((env.reset()[0] if terminated or truncated else obs)["image"])
            expected.append(np.stack(row))
        assert all(np.array_equal(got, want) for got, want in zip(frames, expected, strict=True))
        assert len({frame.tobytes() for frame in frames[-1]}) == 3  # three different scenes, not one drawn thrice
    finally:
        vec_env.close()
        for env in own:
            env.close()
