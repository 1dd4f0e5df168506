"""Held-out evaluation splits: named waters, optics and scenery that no training range reaches.

A split is data, not a code path: the noise and scenery settings a reset carries, so the same evaluation engine
plays it on a live sim or in process (`swimm eval --suite`). Each split lies outside the training randomisation
(:data:`TRAINING_NOISE`, the widest noise any shipped model was trained on, and :data:`TRAINING_SCENE`, the varied
world's ranges) along at least one axis, and :meth:`Split.outside_training` says along which; a test checks every
split against it, so a split can never quietly become part of training. The field's held-out splits
(DMControl-GB, Distracting Control Suite) are built the same way: train on one distribution, report the drop on
shifts of colour, texture and sensor never seen.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_service.noise import EFFECTS, PRESETS, WATER_COLOURS, NoiseSettings
from sim_service.scenery import PRESETS as SCENE_PRESETS
from sim_service.scenery import RANGE_FIELDS, SceneSettings

#: The widest noise randomisation in any shipped model's training: the noise-robust CMVAE's paired frames drew
#: every effect between none and the harsh preset in a mix of natural water colours (docs/encoder.md); the
#: policies trained under at most the murky preset, which lies inside it (tests check both).
TRAINING_NOISE = dataclasses.replace(PRESETS["harsh"], randomise=True)
#: How far (RGB units) a water colour may lie from the training colours' path and still count as seen.
COLOUR_TOLERANCE = 12.0


#: The widest scenery any model trains under (sim_service.scenery's ``wide``, which holds ``varied``).
TRAINING_SCENE = SCENE_PRESETS["wide"]


@dataclass(frozen=True)
class Split:
    """One held-out condition: what a reader calls it, why it is held out, and the settings a reset carries."""

    name: str
    about: str
    noise: NoiseSettings = field(default_factory=NoiseSettings)
    scene: SceneSettings = field(default_factory=SceneSettings)  # the plain world unless the split is scenery

    def reset_options(self) -> dict[str, Any]:
        """The options every episode's reset carries to play this split (a live sim's other envs are untouched).

        Both always travel, so a split never inherits the water or the scenery of the condition played before it.
        """
        return {"noise": dataclasses.asdict(self.noise), "scene": dataclasses.asdict(self.scene)}

    def outside_training(self) -> list[str]:
        """Why this split lies outside training: its noise's axes, and its scenery's where it is not the plain
        world (the world every shipped model trained in)."""
        scenery = scene_outside_training(self.scene) if self.scene.preset != "plain" else []
        return outside_training(self.noise) + scenery


def _water(colour: tuple[int, int, int], **effects: float) -> NoiseSettings:
    return NoiseSettings(fog_color=list(colour), **effects)


def _scenery(**ranges: list[float]) -> SceneSettings:
    """The varied world with ``ranges`` replacing its training ranges."""
    return SceneSettings(preset="varied", **ranges)


#: The suite, in the order tables list it. Strengths are chosen a clear step beyond the training range's edge
#: (docs/eval_report.md, "Held-out waters"), not at its edge, so a split tests generalisation, not luck.
SPLITS: dict[str, Split] = {
    split.name: split
    for split in (
        Split("tannin", "murky water stained brown-red, a colour no training water had",
              _water((75, 48, 28), fog=0.12, grain=6.0, depth_of_field=1.5)),
        Split("turbid", "a coastal colour, far murkier than training (fog 0.22 against at most 0.15)",
              _water((20, 70, 90), fog=0.22, grain=4.0)),
        Split("bright", "clear water lit brighter than any training water (pale backscatter)",
              _water((150, 200, 215), fog=0.06)),
        Split("dark", "dark water that eats colour with distance (attenuation 0.25 against at most 0.12)",
              _water((4, 12, 22), fog=0.08, attenuation=0.25)),
        Split("sensor", "sensor-side effects beyond training: marine snow, shot noise and JPEG",
              NoiseSettings(marine_snow=30.0, shot_noise=20.0, jpeg_quality=20)),
        Split("optics", "a softer, shakier, grainier camera than training: focus, blur, distortion and grain",
              NoiseSettings(depth_of_field=4.0, motion_blur=3.0, distortion=0.4, grain=14.0)),
        Split("seabed", "a varied world over a rougher seabed than training: higher mounds, more rocks and seagrass",
              scene=_scenery(relief_m=[3.5, 4.5], rocks=[10, 12], seagrass=[20, 24])),
        Split("low-sun", "a varied world under a low, dim sun with more and stronger light shafts than training",
              scene=_scenery(sun_intensity=[0.3, 0.45], sun_elevation_deg=[15.0, 30.0], light_shafts=[4, 6],
                             shaft_strength=[0.2, 0.25])),
        Split("shoals", "a varied world with more and larger fish shoals and denser particles than training",
              scene=_scenery(fish_shoals=[3, 3], fish_per_shoal=[7, 8], particles=[40, 60])),
    )
}  # fmt: skip


def outside_training(noise: NoiseSettings, training: NoiseSettings = TRAINING_NOISE) -> list[str]:
    """The axes along which ``noise`` lies outside what ``training`` (read as randomised maxima) can draw.

    Empty means a training episode could have drawn these settings. A colour counts only where it shows (fog or
    attenuation on), and only when it lies farther than :data:`COLOUR_TOLERANCE` from every mix of two
    neighbouring training colours, the set `draw_episode_noise` draws from.
    """
    noise, training = noise.resolved(), training.resolved()
    reasons = []
    for name in EFFECTS:
        value, limit = getattr(noise, name), getattr(training, name)
        if name == "jpeg_quality":
            if value > 0 and (limit == 0 or value < limit):
                reasons.append(f"jpeg_quality {value} below the training's lowest {limit or 'none (JPEG off)'}")
        elif value > limit:
            reasons.append(f"{name} {value:g} above the training's {limit:g}")
    if noise.fog > 0 or noise.attenuation > 0:
        gap = colour_distance(noise.fog_color)
        if gap > COLOUR_TOLERANCE:
            reasons.append(f"water colour {list(noise.fog_color)} {gap:.0f} RGB units from every training colour")
    if noise.attenuation > 0 and list(noise.attenuation_rgb) != list(training.attenuation_rgb):
        reasons.append(f"attenuation_rgb {list(noise.attenuation_rgb)} never trained on")
    if noise.depth_of_field > 0 and noise.focus_m != training.focus_m:
        reasons.append(f"focus_m {noise.focus_m:g} never trained on")
    return reasons


def scene_outside_training(scene: SceneSettings, training: SceneSettings = TRAINING_SCENE) -> list[str]:
    """The scenery ranges of ``scene`` that lie wholly outside ``training``'s (so no training episode draws them).

    An element switched off ([]) is outside a training range that always draws it, and seabed looks count when
    none of them was trained on.
    """
    scene, training = scene.resolved(), training.resolved()
    reasons = []
    if scene.seabed_textures and not set(scene.seabed_textures) & set(training.seabed_textures):
        reasons.append(f"seabed textures {scene.seabed_textures} never trained on")
    for name in RANGE_FIELDS:
        held, trained = getattr(scene, name), getattr(training, name)
        if held == trained or not trained:
            continue
        if not held or held[0] > trained[1] or held[1] < trained[0]:
            reasons.append(f"{name} {held or 'off'} outside the training's {trained}")
    return reasons


def colour_distance(colour: list[int] | tuple[int, ...]) -> float:
    """Euclidean RGB distance from ``colour`` to the nearest mix of two neighbouring :data:`WATER_COLOURS`."""
    point = np.asarray(colour, dtype=float)
    nearest = np.inf
    for start, end in zip(WATER_COLOURS, WATER_COLOURS[1:], strict=False):
        a, b = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
        t = np.clip(np.dot(point - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
        nearest = min(nearest, float(np.linalg.norm(point - (a + t * (b - a)))))
    return nearest


def resolve_splits(names: list[str]) -> list[Split]:
    """The named splits in the suite's order (``all`` or no names: every split); an unknown name is refused."""
    if not names or names == ["all"]:
        return list(SPLITS.values())
    unknown = [name for name in names if name not in SPLITS]
    if unknown:
        raise ValueError(f"unknown split {', '.join(unknown)}; choose from all, {', '.join(SPLITS)}")
    return [SPLITS[name] for name in dict.fromkeys(names)]
