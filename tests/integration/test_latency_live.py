"""Camera and control delays reach a live sim through a reset's options, and only the env that asked for them.

Real processes: a router and a sim; a ProxyEnv over Zenoh asks its env for delays at a reset, and the frames it
gets back must be those an in-process World with the same delays renders (a world's frames are a pure function of
its seed, settings and actions).
"""

from __future__ import annotations

import numpy as np
import pytest

from learner_service.proxy_env import ProxyEnv, ProxySettings
from learner_service.task import TaskSettings, episode_seed
from sim_service.latency import LatencySettings
from sim_service.settings import WorldSettings
from sim_service.world import World
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

SEED = 777
STEPS = 8
DELAYED = LatencySettings(observation_delay=2, action_delay=1, control_period=2)


def world_frames(latency: LatencySettings, commands: list[tuple[float, ...]]) -> np.ndarray:
    world = World(WorldSettings(latency=latency))
    try:
        frames = [world.reset(episode_seed(SEED, 1))[1]]
        frames += [world.step(command)[1] for command in commands]
        return np.stack(frames)
    finally:
        world.close()


def test_a_reset_option_sets_a_live_envs_delays(group, zenoh_router, namespace, zenoh_settings) -> None:
    start_sim(group, zenoh_router, namespace)
    task = TaskSettings(obs="image", max_steps=100)
    env = ProxyEnv(task, ProxySettings(zenoh_settings(zenoh_router), channel="eval", role="eval"), "0")
    actions = [np.array([0.8, 0.6 * (-1) ** step], np.float32) for step in range(STEPS)]
    try:
        frames = [env.reset(seed=SEED, options={"latency": vars(DELAYED)})[0]["image"]]
        frames += [env.step(action)[0]["image"] for action in actions]
        commands = [env.task.to_sim_action(action) for action in actions]
        with pytest.raises(RuntimeError, match="latency: unknown setting 'lag'"):
            env.reset(options={"latency": {"lag": 3}})
    finally:
        env.close()
    np.testing.assert_array_equal(np.stack(frames), world_frames(DELAYED, commands))
    assert not np.array_equal(np.stack(frames), world_frames(LatencySettings(), commands))
