"""Image noise: each effect is exact identity when off and moves the image the physical way when on."""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
import pytest

from services import settings as settings_module
from sim_service import noise
from sim_service.noise import ImageNoise, NoiseSettings

SIZE = 64
FOCUS_M = 6.0


def _texture(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)


def _checkerboard(block: int) -> np.ndarray:
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    board = ((ys // block + xs // block) % 2 * 200 + 30).astype(np.uint8)
    return np.repeat(board[..., None], 3, axis=2)


def _plaid(period: int) -> np.ndarray:
    """Vertical plus horizontal stripes, I = a(x) + b(y): blur along one axis leaves the other's edges intact."""
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    plaid = (40 + 80 * (xs // period % 2) + 80 * (ys // period % 2)).astype(np.uint8)
    return np.repeat(plaid[..., None], 3, axis=2)


def _depth(value: float) -> np.ndarray:
    return np.full((SIZE, SIZE), value, dtype=np.float32)


def _apply(
    settings: NoiseSettings,
    image: np.ndarray,
    depth: np.ndarray | None = None,
    seed: int = 0,
    motion_px: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    return ImageNoise(settings).apply(image, depth, np.random.default_rng(seed), motion_px)


def _gradient_energy(image: np.ndarray, axis: int) -> float:
    return float(np.square(np.diff(image.astype(np.float64), axis=axis)).mean())


def test_defaults_are_off_and_bit_exact_identity():
    settings = NoiseSettings()
    assert not settings.enabled and not settings.needs_depth
    image = _texture()
    out = _apply(settings, image)
    assert out.dtype == np.uint8 and out is not image
    np.testing.assert_array_equal(out, image)


@pytest.mark.parametrize(
    ("settings", "depth", "motion_px"),
    [
        (NoiseSettings(fog=0.2), _depth(0.0), (0.0, 0.0)),  # nothing between camera and surface: no fog
        (NoiseSettings(depth_of_field=3.0), _depth(FOCUS_M), (0.0, 0.0)),  # everything in focus
        (NoiseSettings(motion_blur=2.0), None, (0.0, 0.0)),  # camera and scene still
        (NoiseSettings(motion_blur=2.0), None, (1e-5, 0.0)),  # below a thousandth of a pixel
    ],
)
def test_enabled_effect_with_nothing_to_do_is_bit_exact_identity(settings, depth, motion_px):
    image = _texture(1)
    np.testing.assert_array_equal(_apply(settings, image, depth, motion_px=motion_px), image)


def test_fog_pulls_far_pixels_toward_water_colour_more_than_near_ones():
    density, near_m, far_m = 0.05, 2.0, 20.0
    settings = NoiseSettings(fog=density)
    image = np.full((SIZE, SIZE, 3), 255, dtype=np.uint8)
    depth = _depth(near_m)
    depth[:, SIZE // 2 :] = far_m
    depth[0, -1] = np.inf  # nothing hit: pure water
    out = _apply(settings, image, depth).astype(np.float64)
    colour = np.array(settings.fog_color, dtype=np.float64)
    for column, metres in ((0, near_m), (SIZE - 1, far_m)):
        visibility = math.exp(-((density * metres) ** 2))
        np.testing.assert_allclose(out[5, column], 255 * visibility + colour * (1 - visibility), atol=1.0)
    near_gap = np.abs(out[5, 0] - colour).sum()
    far_gap = np.abs(out[5, -1] - colour).sum()
    assert far_gap < 0.45 * near_gap  # visibility 0.37 at 20 m against 0.99 at 2 m
    np.testing.assert_array_equal(out[0, -1], colour)


def test_grain_std_matches_setting_and_is_monochrome():
    grain = 10.0
    image = np.full((256, 256, 3), 128, dtype=np.uint8)
    out = ImageNoise(NoiseSettings(grain=grain)).apply(image, None, np.random.default_rng(3))
    noise = out.astype(np.float64) - 128
    assert abs(noise.std() - grain) < 0.3
    assert abs(noise.mean()) < 0.2
    np.testing.assert_array_equal(out[..., 0], out[..., 2])


def test_distortion_keeps_the_centre_and_pulls_edge_content_inward():
    k1, line_x = 0.3, 56
    image = np.full((SIZE, SIZE, 3), 40, dtype=np.uint8)
    image[:, line_x] = 250
    image[30:34, 30:34] = (200, 10, 90)
    out = _apply(NoiseSettings(distortion=k1), image)
    np.testing.assert_array_equal(out[31:33, 31:33], image[31:33, 31:33])
    # Output column x samples source x_s = c + (x - c)(1 + k1 ((x - c) / 32)^2): the line lands near x = 53.1.
    moved_to = int(np.argmax(out[31, :, 0]))
    assert moved_to in (53, 54)
    assert out[31, line_x, 0] == 40  # the original column now shows background from further out


def test_horizontal_motion_blur_smooths_horizontal_gradients_only():
    image = _plaid(8)
    out = _apply(NoiseSettings(motion_blur=1.0), image, motion_px=(4.0, 0.0))
    horizontal = _gradient_energy(out, axis=1) / _gradient_energy(image, axis=1)
    vertical = _gradient_energy(out, axis=0) / _gradient_energy(image, axis=0)
    assert horizontal < 0.5
    assert vertical > 0.99


def test_motion_blur_grows_with_the_setting():
    image = _checkerboard(8)
    energies = [
        _gradient_energy(_apply(NoiseSettings(motion_blur=scale), image, motion_px=(0.0, 3.0)), axis=0)
        for scale in (0.5, 1.0, 2.0)
    ]
    assert energies[0] > energies[1] > energies[2]


def test_depth_of_field_blurs_far_pixels_and_keeps_focused_ones():
    image = _checkerboard(2)
    depth = _depth(FOCUS_M)
    depth[:, SIZE // 2 :] = 60.0  # circle of confusion 0.9 of the largest
    out = _apply(NoiseSettings(depth_of_field=3.0, focus_m=FOCUS_M), image, depth)
    np.testing.assert_array_equal(out[:, : SIZE // 2], image[:, : SIZE // 2])
    far = slice(SIZE // 2 + 4, SIZE)
    ratio = _gradient_energy(out[:, far], axis=1) / _gradient_energy(image[:, far], axis=1)
    assert ratio < 0.1


def test_depth_of_field_blurs_near_pixels_too():
    image = _checkerboard(2)
    near = _apply(NoiseSettings(depth_of_field=3.0, focus_m=FOCUS_M), image, _depth(FOCUS_M / 2))
    assert _gradient_energy(near, axis=1) < 0.1 * _gradient_energy(image, axis=1)


def _everything() -> NoiseSettings:
    return NoiseSettings(fog=0.08, grain=6.0, depth_of_field=2.5, distortion=0.2, motion_blur=1.0)


def test_same_seed_same_bytes_and_other_seed_other_bytes():
    image, depth = _texture(4), np.random.default_rng(5).uniform(1, 30, (SIZE, SIZE)).astype(np.float32)
    first = _apply(_everything(), image, depth, seed=11, motion_px=(2.5, -1.0))
    again = _apply(_everything(), image, depth, seed=11, motion_px=(2.5, -1.0))
    other = _apply(_everything(), image, depth, seed=12, motion_px=(2.5, -1.0))
    assert first.tobytes() == again.tobytes()
    assert first.tobytes() != other.tobytes()


def test_inputs_are_not_modified():
    image, depth = _texture(6), _depth(9.0)
    image_before, depth_before = image.copy(), depth.copy()
    _apply(_everything(), image, depth, motion_px=(3.0, 0.0))
    np.testing.assert_array_equal(image, image_before)
    np.testing.assert_array_equal(depth, depth_before)


@pytest.mark.parametrize("settings", [NoiseSettings(fog=0.1), NoiseSettings(depth_of_field=2.0)])
def test_depth_effects_without_depth_raise(settings):
    with pytest.raises(ValueError, match="depth"):
        _apply(settings, _texture())


def test_depth_map_of_wrong_size_raises():
    with pytest.raises(ValueError, match="shape"):
        _apply(NoiseSettings(fog=0.1), _texture(), np.ones((32, 32), dtype=np.float32))


@pytest.mark.parametrize(
    "settings",
    [
        NoiseSettings(grain=-1.0),
        NoiseSettings(focus_m=0.0),
        NoiseSettings(fog_color=[0, 300, 0]),
        NoiseSettings(fog_color=[1, 2]),
    ],
)
def test_invalid_settings_raise(settings):
    with pytest.raises(ValueError):
        ImageNoise(settings)


def test_settings_become_noise_flags():
    @dataclasses.dataclass
    class Holder:
        noise: NoiseSettings = dataclasses.field(default_factory=NoiseSettings)

    parser = argparse.ArgumentParser()
    settings_module.add_arguments(parser, Holder)
    args = parser.parse_args(["--noise-fog", "0.1", "--noise-fog-color", "10", "20", "30"])
    loaded = settings_module.load(Holder, args, environ={"SWIMM_NOISE_GRAIN": "4.5"})
    assert loaded.noise == NoiseSettings(fog=0.1, fog_color=[10, 20, 30], grain=4.5)
    assert loaded.noise.enabled and loaded.noise.needs_depth


# --- the water model, marine snow, sensor effects -----------------------------------------------------------


def test_attenuation_takes_red_first_and_far_pixels_become_the_water_colour():
    settings = NoiseSettings(attenuation=0.3, attenuation_rgb=[1.0, 0.45, 0.3], fog_color=[20, 70, 90])
    white = np.full((SIZE, SIZE, 3), 255, dtype=np.uint8)
    near = _apply(settings, white, _depth(2.0)).astype(float).mean(axis=(0, 1))
    far = _apply(settings, white, _depth(200.0)).astype(float).mean(axis=(0, 1))
    assert near[0] < near[1] < near[2]  # red decays fastest, blue slowest
    np.testing.assert_allclose(far, settings.fog_color, atol=1)  # nothing of the scene survives 200 m of water
    transmission_red = math.exp(-0.3 * 1.0 * 2.0)
    assert near[0] == pytest.approx(255 * transmission_red + 20 * (1 - transmission_red), abs=1)


def test_marine_snow_brightens_a_dark_frame_in_small_spots_and_more_with_more_snow():
    dark = np.full((SIZE, SIZE, 3), 10, dtype=np.uint8)
    light = _apply(NoiseSettings(marine_snow=3.0), dark, seed=1)
    heavy = _apply(NoiseSettings(marine_snow=60.0), dark, seed=1)
    assert (light >= dark).all() and (heavy >= dark).all()  # particles only add light here
    lit_light, lit_heavy = (light > 20).any(axis=2).mean(), (heavy > 20).any(axis=2).mean()
    assert 0 < lit_light < 0.05 and lit_heavy > 4 * lit_light


def test_shot_noise_grows_with_the_signal_and_is_zero_on_black():
    flat = lambda value: np.full((SIZE, SIZE, 3), value, dtype=np.uint8)  # noqa: E731
    settings = NoiseSettings(shot_noise=20.0)
    spread = {value: _apply(settings, flat(value), seed=2).astype(float).std() for value in (0, 50, 200)}
    assert spread[0] == 0.0
    assert spread[200] == pytest.approx(spread[50] * 2.0, rel=0.1)  # std as sqrt(signal): sqrt(200/50) = 2


def test_jpeg_compression_loses_more_at_lower_quality():
    image = _texture(8)
    error = {q: np.abs(_apply(NoiseSettings(jpeg_quality=q), image).astype(float) - image).mean() for q in (95, 20)}
    assert 0 < error[95] < error[20]


# --- presets, severity, randomisation ---------------------------------------------------------------------


def test_presets_fill_the_effects_left_at_zero_and_unknown_presets_are_refused():
    murky = NoiseSettings(preset="murky").resolved()
    assert murky == dataclasses.replace(noise.NOISY_PRESET, preset="off")
    stronger = NoiseSettings(preset="murky", fog=0.5).resolved()
    assert stronger.fog == 0.5 and stronger.grain == noise.NOISY_PRESET.grain
    harsh = noise.PRESETS["harsh"]
    stronger_effects = [name for name in noise.EFFECTS if name != "jpeg_quality"]
    assert all(getattr(harsh, name) >= getattr(noise.NOISY_PRESET, name) for name in stronger_effects)
    with pytest.raises(ValueError, match="unknown noise preset 'soup'"):
        ImageNoise(NoiseSettings(preset="soup"))


def test_severity_scales_the_chosen_effects_and_switches_the_others_off():
    harsh = noise.PRESETS["harsh"]
    assert not noise.scaled(harsh, 0.0).enabled
    assert noise.scaled(harsh, 1.0) == dataclasses.replace(harsh, preset="off")
    fog_only = noise.scaled(harsh, 1.5, ("fog", "jpeg_quality"))
    assert fog_only.fog == 1.5 * harsh.fog and fog_only.grain == 0 and fog_only.attenuation == 0
    assert fog_only.jpeg_quality == 100 - 1.5 * (100 - harsh.jpeg_quality)
    assert noise.scaled(harsh, 5.0).jpeg_quality == 1  # the lowest quality JPEG has
    with pytest.raises(ValueError, match="unknown noise effects"):
        noise.scaled(harsh, 1.0, ("smoke",))


def test_an_episode_draw_lies_inside_the_ranges_and_follows_the_seed():
    maxima = dataclasses.replace(noise.PRESETS["harsh"], randomise=True)
    draws = [noise.draw_episode_noise(maxima, np.random.default_rng(seed)) for seed in range(200)]
    assert draws[7] == noise.draw_episode_noise(maxima, np.random.default_rng(7))
    for name in noise.EFFECTS:
        values = np.array([getattr(d, name) for d in draws], float)
        top = getattr(maxima, name)
        if name == "jpeg_quality":
            assert values.min() >= top and values.max() <= 100
        else:
            assert values.min() >= 0 and values.max() <= top and values.max() > 0.9 * top and values.min() < 0.1 * top
    colours = np.array([d.fog_color for d in draws], float)
    low, high = np.min(noise.WATER_COLOURS, axis=0), np.max(noise.WATER_COLOURS, axis=0)
    assert (colours >= low).all() and (colours <= high).all() and len({tuple(c) for c in colours}) > 50
    assert not any(d.randomise for d in draws)
    mixed = [noise.draw_episode_noise(dataclasses.replace(maxima, clean_share=0.3), np.random.default_rng(seed))
             for seed in range(200)]  # fmt: skip
    assert 0.2 < np.mean([not d.enabled for d in mixed]) < 0.4


@pytest.mark.parametrize(
    "settings",
    [
        NoiseSettings(jpeg_quality=101),
        NoiseSettings(attenuation_rgb=[1.0, -0.1, 0.2]),
        NoiseSettings(marine_snow=-1),
        NoiseSettings(clean_share=1.5),
    ],
)
def test_invalid_new_settings_raise(settings):
    with pytest.raises(ValueError):
        ImageNoise(settings)


def test_preset_and_randomise_come_from_flags_yaml_and_the_environment(tmp_path):
    @dataclasses.dataclass
    class Holder:
        noise: NoiseSettings = dataclasses.field(default_factory=NoiseSettings)

    config = tmp_path / "sim.yaml"
    config.write_text("noise:\n  preset: harsh\n  jpeg_quality: 70\n")
    parser = argparse.ArgumentParser()
    settings_module.add_arguments(parser, Holder)
    args = parser.parse_args(["--noise-randomise"])
    loaded = settings_module.load(Holder, args, config, environ={"SWIMM_NOISE_MARINE_SNOW": "4"})
    assert (loaded.noise.preset, loaded.noise.randomise, loaded.noise.jpeg_quality) == ("harsh", True, 70)
    assert loaded.noise.resolved().marine_snow == 4.0 and loaded.noise.resolved().fog == noise.PRESETS["harsh"].fog


def test_the_shipped_randomised_noise_config_loads_as_sim_settings():
    from pathlib import Path

    from sim_service.settings import SimSettings

    config = Path(noise.__file__).parent / "configs" / "randomised_noise.yaml"
    sim = settings_module.load(SimSettings, None, config, environ={})
    assert sim.world.noise.randomise and sim.world.noise.resolved().enabled and 0 < sim.world.noise.clean_share < 1
