"""ProxyEnv and ProxyVecEnv against real `swimm router` and `swimm sim` processes: env checkers, VecEnv semantics,
claims (refused by name, released on close, lapsed with the holder's liveliness) and a timeout naming the sim."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.vec_env import DummyVecEnv

from learner_service.inprocess_env import TrackingEnv
from learner_service.link import StepTimeout
from learner_service.proxy_env import ClaimRefused, ProxyEnv, ProxySettings, ProxyVecEnv
from learner_service.task import TaskSettings, episode_seed
from services.procs import ProcessGroup
from tests.integration.conftest import start_sim

BASE_SEED = 97


@pytest.fixture
def served(processes: ProcessGroup, namespace, zenoh_settings):
    """Start a router and a sim (two train envs) and return a factory of ProxySettings on them."""
    endpoint = processes.start_router()
    sim = start_sim(processes, endpoint, namespace, "--train-envs", "2", "--eval-envs", "0", "--claim-grace-s", "0.5")

    def settings(**overrides) -> ProxySettings:
        return ProxySettings(zenoh=zenoh_settings(endpoint), **overrides)

    settings.sim = sim  # type: ignore[attr-defined]
    return settings


# Positions and latents have no natural bound, so unbounded Boxes are on purpose; gymnasium and SB3 warn about them.
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")
@pytest.mark.filterwarnings("ignore:.*unbounded.*")
@pytest.mark.parametrize("obs", ["state", "image"])
def test_proxy_env_passes_gymnasium_and_sb3_env_checkers(served, obs) -> None:
    env = ProxyEnv(TaskSettings(obs=obs), served(), base_seed=BASE_SEED)
    gymnasium_check_env(env, skip_render_check=True)
    sb3_check_env(env, warn=False, skip_render_check=True)
    env.close()


@pytest.mark.slow
def test_proxy_vec_env_behaves_as_a_dummy_vec_env_of_tracking_envs(served) -> None:
    """Two remote envs stepped together: same observations, rewards, dones, auto-resets and infos as in-process."""
    task = TaskSettings(obs="state", max_steps=25)  # short episodes: time-limit truncations and early endings both
    remote = ProxyVecEnv(task, served(envs=("0", "1")), base_seed=BASE_SEED)
    local = DummyVecEnv([lambda i=i: TrackingEnv(task, base_seed=BASE_SEED + i) for i in range(2)])
    assert remote.num_envs == 2
    assert remote.observation_space == local.observation_space and remote.action_space == local.action_space

    observations = remote.reset()
    np.testing.assert_array_equal(observations, local.reset())
    assert observations.shape == (2, *remote.observation_space.shape)
    assert [info["seed"] for info in remote.reset_infos] == [episode_seed(BASE_SEED + i, 1) for i in range(2)]

    actions = np.random.default_rng(3).uniform(-1, 1, (80, 2, 2)).astype(np.float32)
    done_steps = 0
    for step_actions in actions:
        remote.step_async(step_actions)  # both actions are on their way before any reply is awaited
        obs, rewards, dones, infos = remote.step_wait()
        local_obs, local_rewards, local_dones, local_infos = local.step(step_actions)
        np.testing.assert_array_equal(obs, local_obs)
        np.testing.assert_array_equal(rewards, local_rewards)
        np.testing.assert_array_equal(dones, local_dones)
        for info, local_info in zip(infos, local_infos, strict=True):
            assert {k: info[k] for k in ("ep", "cause", "TimeLimit.truncated", "telemetry")} == {
                k: local_info[k] for k in ("ep", "cause", "TimeLimit.truncated", "telemetry")
            }
            if "terminal_observation" in local_info:
                np.testing.assert_array_equal(info["terminal_observation"], local_info["terminal_observation"])
                done_steps += 1
            else:
                assert "terminal_observation" not in info
        assert all(remote.observation_space.contains(row) for row in obs)
    assert done_steps >= 3  # episodes of at most 25 steps ended and were auto-reset

    remote.seed(5)  # SB3's seeding: sub-env i restarts the episode sequence of base seed 5 + i
    np.testing.assert_array_equal(remote.reset(), [TrackingEnv(task, base_seed=5 + i).reset()[0] for i in range(2)])
    remote.close()
    local.close()


@pytest.mark.slow
def test_a_taken_env_is_refused_naming_its_holder_and_free_again_after_close(served) -> None:
    task = TaskSettings(obs="state")
    first = ProxyEnv(task, served())
    with pytest.raises(ClaimRefused, match=f"held by {first.holder}"):
        ProxyEnv(task, served())
    first.reset()
    first.step((0.5, 0.0))  # the holder keeps driving after the refusal
    first.close()
    second = ProxyEnv(task, served())  # released on close
    assert second.reset()[1]["ep"] == 1  # the sim's episode count went on; the task's restarts at 1
    second.close()


@pytest.mark.slow
def test_a_claim_lapses_when_the_holders_session_dies(served) -> None:
    task = TaskSettings(obs="state")
    gone = ProxyEnv(task, served())
    gone.session.close()  # as a crash: no release, the liveliness token just disappears
    deadline = time.monotonic() + 10
    while True:
        try:
            successor = ProxyEnv(task, served())
            break
        except ClaimRefused:
            assert time.monotonic() < deadline, "the dead holder's claim never lapsed"
            time.sleep(0.2)
    successor.reset()
    successor.close()


@pytest.mark.slow
def test_a_stopped_sim_gives_a_step_timeout_naming_the_sim(served, processes: ProcessGroup) -> None:
    env = ProxyEnv(TaskSettings(obs="state"), served(step_timeout_s=0.3, max_retries=2))
    env.reset()
    env.step((0.1, 0.1))
    processes.stop(served.sim)
    started = time.monotonic()
    with pytest.raises(StepTimeout, match="swimm sim"):
        env.step((0.1, 0.1))
    assert time.monotonic() - started < 5  # 3 tries of 0.3 s, bounded
    env.close()


@pytest.mark.slow
def test_a_reset_sent_while_the_sim_restarts_claims_the_env_again(served, processes, namespace) -> None:
    """The sim dies with a reset unanswered; the re-sent reset reaches its successor, which refuses it as unclaimed:
    the env is claimed again and the episode starts there (the race a supervised `swimm up` meets)."""
    env = ProxyEnv(TaskSettings(obs="state"), served(step_timeout_s=0.5, max_retries=40))
    env.reset()
    processes.stop(served.sim)
    restart = threading.Timer(1.0, start_sim, (processes, served().zenoh.connect[0], namespace, "--train-envs", "2"))
    restart.start()
    obs, info = env.reset()  # first sent to no sim at all
    restart.join()
    assert env.sims_lost == 1 and env.observation_space.contains(obs)
    env.step((0.1, 0.1))
    env.close()


def test_settings_are_checked_before_any_connection() -> None:
    with pytest.raises(ValueError, match="channel"):
        ProxyEnv(TaskSettings(), ProxySettings(channel="test"))
    with pytest.raises(ValueError, match="role"):
        ProxyEnv(TaskSettings(), ProxySettings(role="sim"))
    with pytest.raises(ValueError, match="env id"):
        ProxyVecEnv(TaskSettings(), ProxySettings(envs=("0", "a/b")))
