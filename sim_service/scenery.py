"""The varied world: seabed relief and textures, sunlight from the surface, suspended particles, fish shoals and
the dolphin's look, each drawn per episode from the episode's seed; the paper's plain world is the default.

Why it is built this way: the encoder has to learn the dolphin, not the one seabed and the one light it was
trained under, so training episodes draw their scenery from ranges (:data:`PRESETS` ``"varied"``), and held-out
evaluation draws outside them. The ranges are data: a held-out split is another :class:`SceneSettings`.

This module holds the settings and the draws (no MuJoCo, so the learner's image can read the settings);
sim_service/scenery_model.py puts a drawn scene into the MuJoCo world.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from services.settings import from_message

SEABED_Z = -12.0
#: How many of each element the model holds: the most any setting may ask for (held-out splits included).
CAPACITY = {"mounds": 3, "rocks": 12, "seagrass": 24, "light_shafts": 6, "particles": 60, "fish_shoals": 3}
MAX_FISH_PER_SHOAL = 8
SEABED_TILE_M = 40.0  # mounds, rocks and seagrass repeat every 40 m around the rover (fog hides the seams)
SHAFT_TILE_M = 24.0
PARTICLE_TILE_M = 6.0  # a cube of water around the camera; particles farther than 3 m are below a pixel
FISH_TILE_M = 30.0
MIN_SUN_ELEVATION_DEG = 10.0  # lower suns' shafts would run for kilometres under the surface
DEPTH_FALLOFF = 0.08  # per metre: daylight fades as exp(-0.08 (depth - 4 m)) below the rover's usual depth
NOMINAL_DEPTH = 4.0
#: Seabed looks (name: base colour, mark colour, mark density, texture repeats); "sand" is the plain world's.
SEABED_TEXTURES = {
    "sand": None,
    "rippled": ((0.58, 0.55, 0.42), (0.78, 0.76, 0.62), 0.25, 60),
    "gravel": ((0.42, 0.41, 0.38), (0.22, 0.21, 0.20), 0.45, 80),
    "mud": ((0.30, 0.28, 0.20), (0.40, 0.37, 0.27), 0.10, 30),
    "meadow": ((0.32, 0.38, 0.22), (0.18, 0.26, 0.12), 0.35, 50),
}
RANGE_FIELDS = (
    "relief_m", "rocks", "seagrass", "sun_intensity", "sun_elevation_deg", "light_shafts", "shaft_strength",
    "particles", "fish_shoals", "fish_per_shoal", "dolphin_scale", "dolphin_shade",
)  # fmt: skip


@dataclass
class SceneSettings:
    """Scenery switches; simple field types so `services.settings` turns them into ``--scene-*`` flags.

    Every range is [low, high] (drawn uniformly per episode), [x, x] fixes it, [] switches the element off;
    a field left at None takes the preset's range.
    """

    preset: str = "plain"  # plain (the paper's world) | varied (training ranges) | wide (wider); fields set here win
    seabed_textures: list[str] | None = None  # seabed looks drawn from (sand, rippled, gravel, mud, meadow)
    relief_m: list[float] | None = None  # height range of the seabed's mounds, metres
    rocks: list[int] | None = None  # range of the number of rocks on a 40 m seabed tile
    seagrass: list[int] | None = None  # range of the number of seagrass blades on a 40 m tile
    sun_intensity: list[float] | None = None  # sunlight (sun, surface glow, ambient) relative to the plain world's
    sun_elevation_deg: list[float] | None = None  # sun elevation range (the azimuth is uniform)
    light_shafts: list[int] | None = None  # range of the number of light shafts on a 24 m tile (with the sun on)
    shaft_strength: list[float] | None = None  # opacity range of the light shafts
    particles: list[int] | None = None  # range of the number of suspended particles in a 6 m cube around the camera
    fish_shoals: list[int] | None = None  # range of the number of fish shoals crossing the view
    fish_per_shoal: list[int] | None = None  # range of the number of fish in a shoal
    dolphin_scale: list[float] | None = None  # range of the dolphin's drawn size (its collider stays nominal)
    dolphin_shade: list[float] | None = None  # range of the factor on the dolphin's grey

    @classmethod
    def from_mapping(cls, values: dict) -> SceneSettings:
        """Settings from a message's map (a reset's ``scene``), refusing unknown keys and wrong types by name."""
        settings = from_message(cls, values, "scene")
        settings.resolved()  # validates
        return settings

    def resolved(self) -> SceneSettings:
        """These settings with the preset's ranges filled in where a field is None, checked."""
        if self.preset not in PRESETS:
            raise ValueError(f"unknown scene preset {self.preset!r}; choose one of {', '.join(PRESETS)}")
        base = PRESETS[self.preset]
        names = ("seabed_textures", *RANGE_FIELDS)
        filled = {name: getattr(base, name) if getattr(self, name) is None else getattr(self, name) for name in names}
        resolved = dataclasses.replace(self, **filled)
        _validate(resolved)
        return resolved


def scene_option(value: object) -> SceneSettings | None:
    """A reset's ``scene`` option as `World.reset` takes it: settings from a map, or None (unchanged)."""
    if isinstance(value, dict):
        return SceneSettings.from_mapping(value)
    if value is None or isinstance(value, SceneSettings):
        return value
    raise ValueError(f"'scene' must be a map of scene settings or absent, got {value!r}")


_VARIED = SceneSettings(
    preset="varied", seabed_textures=list(SEABED_TEXTURES), relief_m=[0.5, 2.5], rocks=[0, 8], seagrass=[0, 16],
    sun_intensity=[0.6, 1.3], sun_elevation_deg=[40.0, 90.0], light_shafts=[0, 2], shaft_strength=[0.04, 0.14],
    particles=[5, 20], fish_shoals=[0, 2], fish_per_shoal=[3, 6], dolphin_scale=[0.85, 1.15],
    dolphin_shade=[0.7, 1.25],
)  # fmt: skip
#: Named presets: ``plain`` is the paper's world; ``varied`` holds the training ranges; ``wide`` stretches them.
PRESETS = {
    "plain": SceneSettings(
        preset="plain", seabed_textures=[], relief_m=[], rocks=[], seagrass=[], sun_intensity=[],
        sun_elevation_deg=[], light_shafts=[], shaft_strength=[], particles=[], fish_shoals=[], fish_per_shoal=[],
        dolphin_scale=[], dolphin_shade=[],
    ),
    "varied": _VARIED,
    # The varied world's ranges stretched toward every scenery split without reaching one: lower and stronger
    # suns' shafts, rougher seabeds, more life in the water (docs/encoder.md, "Wider scenery").
    "wide": dataclasses.replace(
        _VARIED, preset="wide", relief_m=[0.5, 3.2], rocks=[0, 9], seagrass=[0, 19], sun_intensity=[0.5, 1.4],
        sun_elevation_deg=[32.0, 90.0], light_shafts=[0, 3], shaft_strength=[0.04, 0.19], particles=[5, 35],
    ),
}  # fmt: skip


def _validate(settings: SceneSettings) -> None:
    unknown = set(settings.seabed_textures) - set(SEABED_TEXTURES)
    if unknown:
        raise ValueError(f"unknown seabed textures {sorted(unknown)}; choose from {', '.join(SEABED_TEXTURES)}")
    for name in RANGE_FIELDS:
        bounds = getattr(settings, name)
        if len(bounds) not in (0, 2) or (bounds and not 0 <= bounds[0] <= bounds[1]):
            raise ValueError(
                f"scene setting {name} must be [] (off) or [low, high] with 0 <= low <= high, got {bounds}"
            )
        most = MAX_FISH_PER_SHOAL if name == "fish_per_shoal" else CAPACITY.get(name)
        if bounds and most is not None and bounds[1] > most:
            raise ValueError(f"scene setting {name} may ask for at most {most}, got {bounds}")
    elevation = settings.sun_elevation_deg
    if elevation and not MIN_SUN_ELEVATION_DEG <= elevation[0] <= elevation[1] <= 90:
        raise ValueError(f"scene setting sun_elevation_deg must lie in [{MIN_SUN_ELEVATION_DEG}, 90], got {elevation}")


# --- one episode's draw ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Sun:
    intensity: float
    direction: tuple[float, float, float]  # unit vector the light travels along (downward)


@dataclass(frozen=True)
class EpisodeScene:
    """One episode's concrete scenery; positions are offsets from the rover at the start, on each element's tile.

    Arrays have one row per element in use: mounds (x, y, half length, half width, height, yaw), rocks (x, y,
    half sizes, yaw, tilt), seagrass (x, y, height, lean x, lean y), shafts (x, y, half width, opacity),
    particles (x, y, z, half size), shoals (x, y, z, heading, speed, fish).
    """

    seabed_texture: str | None = None
    mounds: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    rocks: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    seagrass: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    sun: Sun | None = None
    shafts: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    particles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    shoals: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    fish_offsets: np.ndarray = field(default_factory=lambda: np.zeros((0, MAX_FISH_PER_SHOAL, 3)))
    dolphin_scale: float | None = None
    dolphin_shade: float | None = None

    @property
    def plain(self) -> bool:
        """True when nothing is drawn or changed: the plain world's episode."""
        arrays = (self.mounds, self.rocks, self.seagrass, self.shafts, self.particles, self.shoals)
        looks = (self.seabed_texture, self.sun, self.dolphin_scale, self.dolphin_shade)
        return all(len(array) == 0 for array in arrays) and all(value is None for value in looks)


def draw_episode_scene(settings: SceneSettings, rng: np.random.Generator) -> EpisodeScene:
    """One episode's scenery drawn from ``settings``' ranges with ``rng``.

    Every element draws at full capacity whether it is on or not, so one element's setting never shifts
    another's draw; the same generator state gives the same scene.
    """
    s = settings.resolved()
    texture = _pick(s.seabed_textures, rng)
    half = SEABED_TILE_M / 2
    relief = _uniform(s.relief_m, rng)
    mounds = np.column_stack([
        rng.uniform(-half, half, (CAPACITY["mounds"], 2)), rng.uniform(3.0, 8.0, (CAPACITY["mounds"], 2)),
        rng.uniform(0.0, 1.0, CAPACITY["mounds"]) * 0.5 + 0.5, rng.uniform(-math.pi, math.pi, CAPACITY["mounds"]),
    ])  # fmt: skip
    mounds[:, 4] *= relief or 0.0
    rocks = np.column_stack([
        rng.uniform(-half, half, (CAPACITY["rocks"], 2)), rng.uniform(0.15, 0.8, (CAPACITY["rocks"], 3)),
        rng.uniform(-math.pi, math.pi, CAPACITY["rocks"]), rng.uniform(-0.4, 0.4, CAPACITY["rocks"]),
    ])  # fmt: skip
    seagrass = _seagrass(rng, half)
    sun = _sun(s, rng)
    shafts = np.column_stack([
        rng.uniform(-SHAFT_TILE_M / 2, SHAFT_TILE_M / 2, (CAPACITY["light_shafts"], 2)),
        rng.uniform(0.3, 1.2, CAPACITY["light_shafts"]),
        np.full(CAPACITY["light_shafts"], _uniform(s.shaft_strength, rng) or 0.0),
    ])  # fmt: skip
    particles = np.column_stack([
        rng.uniform(-PARTICLE_TILE_M / 2, PARTICLE_TILE_M / 2, (CAPACITY["particles"], 3)),
        rng.uniform(0.006, 0.018, CAPACITY["particles"]),
    ])  # fmt: skip
    shoals, fish_offsets = _shoals(s, rng)
    counts = {name: _count(getattr(s, name), rng) for name in ("rocks", "seagrass", "light_shafts", "particles")}
    return EpisodeScene(
        seabed_texture=None if texture in (None, "sand") else texture,
        mounds=mounds if relief else mounds[:0],
        rocks=rocks[: counts["rocks"]],
        seagrass=seagrass[: counts["seagrass"]],
        sun=sun,
        shafts=shafts[: counts["light_shafts"] if sun is not None else 0],  # shafts follow the sun's rays
        particles=particles[: counts["particles"]],
        shoals=shoals,
        fish_offsets=fish_offsets,
        dolphin_scale=_uniform(s.dolphin_scale, rng),
        dolphin_shade=_uniform(s.dolphin_shade, rng),
    )


def _uniform(bounds: list[float], rng: np.random.Generator) -> float | None:
    """A uniform draw in [low, high], or None for an element that is off; one draw either way."""
    value = rng.uniform(0.0, 1.0)
    return None if not bounds else bounds[0] + value * (bounds[1] - bounds[0])


def _count(bounds: list[int], rng: np.random.Generator) -> int:
    """A uniform whole number in [low, high] (0 when off); one draw either way."""
    value = rng.uniform(0.0, 1.0)
    return 0 if not bounds else min(bounds[0] + int(value * (bounds[1] - bounds[0] + 1)), bounds[1])


def _pick(names: list[str], rng: np.random.Generator) -> str | None:
    index = rng.uniform(0.0, 1.0)
    return names[int(index * len(names))] if names else None


def _seagrass(rng: np.random.Generator, half: float) -> np.ndarray:
    """Blades in patches of four round a few patch centres, each blade leaning a little."""
    count = CAPACITY["seagrass"]
    centres = rng.uniform(-half, half, (count // 4, 2)).repeat(4, axis=0)
    return np.column_stack([
        centres + rng.normal(0.0, 0.35, (count, 2)), rng.uniform(0.3, 1.1, count), rng.uniform(-0.3, 0.3, (count, 2)),
    ])  # fmt: skip


def _sun(settings: SceneSettings, rng: np.random.Generator) -> Sun | None:
    intensity = _uniform(settings.sun_intensity, rng)
    elevation = _uniform(settings.sun_elevation_deg, rng)
    azimuth = rng.uniform(-math.pi, math.pi)
    if intensity is None and elevation is None:
        return None
    up = math.radians(90.0 if elevation is None else elevation)
    direction = (-math.cos(up) * math.cos(azimuth), -math.cos(up) * math.sin(azimuth), -math.sin(up))
    return Sun(1.0 if intensity is None else intensity, direction)


def _shoals(settings: SceneSettings, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Shoals ahead of the rover (3 to 10 m, up to 6 m aside) swimming across its view, and their fish's places."""
    count = CAPACITY["fish_shoals"]
    ahead, aside = rng.uniform(3.0, 10.0, count), rng.uniform(-6.0, 6.0, count)
    depth = rng.uniform(-1.5, 1.5, count)
    across = -np.sign(aside) * math.pi / 2 + rng.uniform(-0.5, 0.5, count)  # heading relative to the rover's
    speed = rng.uniform(0.3, 1.0, count)
    fish = np.array([_count(settings.fish_per_shoal, rng) for _ in range(count)], float)
    offsets = rng.normal(0.0, 1.0, (count, MAX_FISH_PER_SHOAL, 3)) * [0.35, 0.35, 0.15]
    shoals = np.column_stack([ahead, aside, depth, across, speed, fish])
    used = _count(settings.fish_shoals, rng)
    return shoals[:used], offsets[:used]
