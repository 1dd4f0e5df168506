"""What `swimm sim` refuses before it serves (observations too large for a low-latency session, worlds it could
not build), and a world that fails as it is built."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from services.low_latency import OBSERVATION_OVERHEAD_BYTES
from services.messages import BatchItem, BatchMsg, ObservationMsg
from services.session import LOW_LATENCY_MAX_MESSAGE_BYTES
from services.settings import SETTINGS_EXIT_CODE, ZenohSettings
from sim_service.responder import check_fits_low_latency
from sim_service.settings import SimSettings, WorldSettings
from sim_service.world import World


def sim_settings(image_size: int, low_latency: bool = True, render: bool = True) -> SimSettings:
    return SimSettings(
        zenoh=ZenohSettings(low_latency=low_latency), world=WorldSettings(image_size=image_size, render=render)
    )


def test_low_latency_takes_images_up_to_its_limit_and_names_the_largest_size_beyond_it():
    check_fits_low_latency(sim_settings(123))  # 123 px: 45 387 image bytes plus the overhead fit in 48 000
    with pytest.raises(ValueError, match=r"--image-size 123 or less"):
        check_fits_low_latency(sim_settings(124))
    check_fits_low_latency(sim_settings(512, low_latency=False))  # the standard transport fragments
    check_fits_low_latency(sim_settings(512, render=False))  # no image, no large message


def test_the_overhead_allowed_for_covers_a_real_observation_with_the_longest_stamps():
    world = World(WorldSettings(image_size=16))
    try:
        telemetry, image = world.reset(3)
        observation = ObservationMsg(env="999", ep=2**63, seq=2**63, telemetry=telemetry, image=image)
        payload = BatchMsg.alone(BatchItem.of("999", observation), "sim-" + "f" * 32, "learner-" + "f" * 32).encode()
    finally:
        world.close()
    assert len(payload) - image.nbytes <= OBSERVATION_OVERHEAD_BYTES
    assert OBSERVATION_OVERHEAD_BYTES < LOW_LATENCY_MAX_MESSAGE_BYTES


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (("--noise-preset", "fogbank"), "unknown noise preset 'fogbank'; choose one of off, murky, harsh"),
        (("--scene-preset", "reef"), "unknown scene preset 'reef'; choose one of plain, varied, wide"),
    ],
)
def test_a_world_no_sim_could_build_is_refused_by_name_before_any_is_built(flags, message):
    result = subprocess.run([sys.executable, "-m", "swimm", "sim", *flags], capture_output=True, text=True, timeout=60)
    assert result.returncode == SETTINGS_EXIT_CODE and f"sim refused its settings: {message}" in result.stderr


def test_a_world_that_cannot_render_ends_the_sim_at_once_saying_why():
    """No GL context can be made (GLX without a display): the sim says so as soon as its worker fails, not after
    the 120 s it allows a worker to build its worlds (the run's 60 s timeout)."""
    env = {key: value for key, value in os.environ.items() if key != "DISPLAY"} | {"MUJOCO_GL": "glx"}
    result = subprocess.run([sys.executable, "-m", "swimm", "sim"], capture_output=True, text=True, timeout=60, env=env)
    assert result.returncode != 0 and "the sim could not build its worlds: " in result.stderr
