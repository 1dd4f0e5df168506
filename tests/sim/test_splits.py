"""The held-out splits: each lies outside every training randomisation, and the check that says so can say no."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from sim_service.noise import PRESETS, WATER_COLOURS, NoiseSettings, draw_episode_noise
from sim_service.scenery import SceneSettings, draw_episode_scene
from sim_service.splits import (
    SPLITS,
    TRAINING_NOISE,
    TRAINING_SCENE,
    outside_training,
    resolve_splits,
    scene_outside_training,
)
from sim_service.world import World

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", list(SPLITS))
def test_every_split_lies_outside_the_training_randomisation(name) -> None:
    assert SPLITS[name].outside_training(), f"split {name} overlaps the training ranges"


def test_no_training_draw_is_called_held_out() -> None:
    """The check is not vacuous: 500 draws of the training randomisation all count as seen, and the presets too."""
    rng = np.random.default_rng(0)
    for _ in range(500):
        drawn = draw_episode_noise(TRAINING_NOISE, rng)
        assert outside_training(drawn) == [], drawn
    for preset in ("off", "murky", "harsh"):
        assert outside_training(PRESETS[preset]) == []


def test_the_policies_training_noise_lies_inside_the_training_noise() -> None:
    """The shipped policies trained on the sim configs below; the splits' training ranges must cover them."""
    for config in ("randomised_noise.yaml", "randomised_noise_latency.yaml", "randomised_world.yaml"):
        values = yaml.safe_load((REPO_ROOT / "sim_service" / "configs" / config).read_text())
        preset = PRESETS[values["noise_preset"]]
        assert outside_training(preset) == [], config
        if "scene_preset" in values:  # the varied world's training ranges, not beyond them
            assert scene_outside_training(SceneSettings(preset=values["scene_preset"])) == [], config


@pytest.mark.parametrize(
    ("change", "axis"),
    [
        ({"fog": 0.2}, "fog 0.2 above"),
        ({"jpeg_quality": 30}, "jpeg_quality 30 below"),
        ({"fog": 0.1, "fog_color": [200, 40, 40]}, "water colour"),
        ({"attenuation": 0.1, "attenuation_rgb": [0.3, 0.45, 1.0]}, "attenuation_rgb"),
    ],
)
def test_each_axis_beyond_training_is_named(change, axis) -> None:
    reasons = outside_training(NoiseSettings(**change))
    assert any(axis in reason for reason in reasons), reasons


def test_a_colour_between_two_training_colours_counts_as_seen() -> None:
    mix = (np.asarray(WATER_COLOURS[1]) + np.asarray(WATER_COLOURS[2])) / 2
    assert outside_training(NoiseSettings(fog=0.1, fog_color=[int(c) for c in mix])) == []


def test_unknown_split_names_are_refused_by_name() -> None:
    assert [split.name for split in resolve_splits(["all"])] == list(SPLITS)
    assert [split.name for split in resolve_splits(["dark", "tannin", "dark"])] == ["dark", "tannin"]
    with pytest.raises(ValueError, match="unknown split lagoon; choose from all, tannin"):
        resolve_splits(["lagoon"])


def test_a_split_reaches_a_world_through_its_reset_options_and_keeps_the_poses() -> None:
    """A split changes what the camera sees, never where anything is."""
    world = World()
    try:
        clean_telemetry, clean_frame = world.reset(7, noise=False)
        split = SPLITS["tannin"]
        noise = NoiseSettings.from_mapping(split.reset_options()["noise"])
        telemetry, frame = world.reset(7, noise=noise)
        assert dataclasses.astuple(telemetry) == dataclasses.astuple(clean_telemetry)
        assert not np.array_equal(frame, clean_frame)
        assert world.noise_settings.fog_color == [75, 48, 28]
    finally:
        world.close()


def test_the_scenery_check_can_say_no_and_names_each_axis() -> None:
    assert scene_outside_training(TRAINING_SCENE) == []
    assert scene_outside_training(SceneSettings(preset="varied")) == []  # the wide ranges hold the varied ones
    assert scene_outside_training(SceneSettings(preset="varied", rocks=[2, 4])) == []  # inside the training range
    reasons = scene_outside_training(SceneSettings(preset="varied", rocks=[10, 11], fish_shoals=[]))
    assert any("rocks [10, 11]" in r for r in reasons) and any("fish_shoals off" in r for r in reasons)


def test_a_scenery_split_draws_outside_the_training_ranges_every_time() -> None:
    """Every draw of a scenery split has at least one element the training ranges never give."""
    for name in ("seabed", "low-sun", "shoals"):
        split, rng = SPLITS[name], np.random.default_rng(1)
        for _ in range(50):
            drawn = draw_episode_scene(split.scene, rng)
            training = TRAINING_SCENE
            assert (drawn.mounds[:, 4].max() > training.relief_m[1] or len(drawn.rocks) > training.rocks[1]
                    or (drawn.sun is not None and drawn.sun.intensity < training.sun_intensity[0])
                    or len(drawn.shoals) > training.fish_shoals[1]), name  # fmt: skip
