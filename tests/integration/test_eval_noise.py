"""`swimm eval` and a live sim's image noise: left as the sim was started unless asked, swept when asked.

Real processes: a router, a sim started with the murky preset, `swimm eval` as its own process. What noise the
sim's eval env renders afterwards is read from its frames: a ProxyEnv resets it to a seed, and the frame must be
the one an in-process World with the expected noise renders for that seed (a world's frames are a pure function
of its seed and settings, noise included).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from learner_service.proxy_env import ProxyEnv, ProxySettings
from learner_service.task import TaskSettings, episode_seed
from sim_service.noise import PRESETS, NoiseSettings, scaled
from sim_service.settings import WorldSettings
from sim_service.splits import SPLITS
from sim_service.world import World
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

SEED = 4242


def eval_env_frame(zenoh_settings, router: str) -> np.ndarray:
    """The frame the sim's eval env answers a reset to episode 1 of SEED with, noise left as the env has it."""
    proxy = ProxySettings(zenoh_settings(router), channel="eval", role="eval", step_timeout_s=10.0)
    env = ProxyEnv(TaskSettings(obs="image", max_steps=10), proxy, "0")
    try:
        obs, _ = env.reset(seed=SEED)
        return obs["image"]
    finally:
        env.close()


def world_frame(noise: NoiseSettings) -> np.ndarray:
    world = World(WorldSettings(noise=noise))
    try:
        return world.reset(episode_seed(SEED, 1))[1]
    finally:
        world.close()


def run_eval(group, router: str, namespace: str, out: Path, *args: str) -> None:
    common = ["--connect", router, "--namespace", namespace, "--algo", "scripted", "--episodes", "1", "--steps",
              "15", "--obs", "image", "--out", str(out), "--no-progress-bar", "--no-figures"]  # fmt: skip
    evaluator = group.start(out.name, "eval", *common, *args)
    assert evaluator.process.wait(timeout=180) == 0, evaluator.log_tail()


def test_eval_leaves_a_live_sims_noise_as_it_was_started_unless_told(
    group, zenoh_router, namespace, zenoh_settings, tmp_path
) -> None:
    start_sim(group, zenoh_router, namespace, "--noise-preset", "murky")
    murky, clean = world_frame(NoiseSettings(preset="murky")), world_frame(NoiseSettings())
    assert not np.array_equal(murky, clean)
    assert np.array_equal(eval_env_frame(zenoh_settings, zenoh_router), murky)
    run_eval(group, zenoh_router, namespace, tmp_path / "kept")
    assert np.array_equal(eval_env_frame(zenoh_settings, zenoh_router), murky)  # the default left it as it was
    run_eval(group, zenoh_router, namespace, tmp_path / "off", "--noise", "off")
    assert np.array_equal(eval_env_frame(zenoh_settings, zenoh_router), clean)  # switched off, as asked


def test_a_noise_sweep_runs_end_to_end_on_a_live_sim(group, zenoh_router, namespace, zenoh_settings, tmp_path) -> None:
    start_sim(group, zenoh_router, namespace)
    out = tmp_path / "sweep"
    run_eval(group, zenoh_router, namespace, out, "--sweep", "--sweep-effects", "all", "fog",
             "--sweep-severities", "0", "1", "--figures")  # fmt: skip
    table = pd.read_csv(out / "sweep.csv")
    assert list(zip(table["effects"], table["severity"], strict=True)) == [("none", 0.0), ("all", 1.0), ("fog", 1.0)]
    assert (table["episodes"] == 1).all() and (out / "sweep.png").is_file()
    # The eval env kept the last condition's noise (fog alone at the harsh preset's strength): the sweep's noise
    # reached the sim, and only through the env it claimed.
    fog = scaled(PRESETS["harsh"], 1.0, ("fog",))
    assert np.array_equal(eval_env_frame(zenoh_settings, zenoh_router), world_frame(fog))


def test_a_suite_plays_the_held_out_splits_on_a_live_sim(group, zenoh_router, namespace, zenoh_settings,
                                                         tmp_path) -> None:  # fmt: skip
    """Each split's water and scenery travel in the resets to the claimed env: it renders the last split's."""
    start_sim(group, zenoh_router, namespace)
    out = tmp_path / "suite"
    run_eval(
        group, zenoh_router, namespace, out, "--suite", "--suite-splits", "tannin", "shoals", "--suite-frames", "2"
    )
    table = pd.read_csv(out / "suite.csv")
    assert list(table["condition"]) == ["clean", "murky", "tannin", "shoals"] and (table["episodes"] == 1).all()
    world = World(WorldSettings())
    try:
        expected = world.reset(episode_seed(SEED, 1), noise=False, scene=SPLITS["shoals"].scene)[1]
    finally:
        world.close()
    assert np.array_equal(eval_env_frame(zenoh_settings, zenoh_router), expected)
