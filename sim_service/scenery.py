"""The varied world: seabed relief and textures, sunlight from the surface, suspended particles, fish shoals and
the dolphin's look, each drawn per episode from the episode's seed; the paper's plain world is the default.

Why it is built this way: the encoder has to learn the dolphin, not the one seabed and the one light it was
trained under, so training episodes draw their scenery from ranges (:data:`PRESETS` ``"varied"``), and held-out
evaluation draws outside them. The ranges are data: a held-out split is another :class:`SceneSettings`.

Cheap on a software renderer: every element is a box, three flat ellipsoids (the mounds) or an eight-faced
mesh (a fish), all attached to one mocap body added after the world's own bodies, so the world's ids do not
move. They live in geom group :data:`SHOWN` while in use and :data:`UNUSED` otherwise; the renderer shows group
:data:`SHOWN` only in a varied episode, so a plain episode draws exactly the frames the plain world always drew.
The seabed, the particles, the light shafts and the shoals are laid out on tiles that wrap around the rover
(each element jumps by a tile when it falls more than half a tile behind), so the rover never leaves them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from services.settings import from_message

SHOWN, UNUSED = 4, 5  # geom groups: drawn in a varied episode / never drawn
SEABED_Z = -12.0
#: How many of each element the model holds: the most any setting may ask for (held-out splits included).
CAPACITY = {"mounds": 3, "rocks": 12, "seagrass": 24, "light_shafts": 6, "particles": 60, "fish_shoals": 3}
MAX_FISH_PER_SHOAL = 8
SEABED_TILE_M = 40.0  # mounds, rocks and seagrass repeat every 40 m around the rover (fog hides the seams)
SHAFT_TILE_M = 24.0
PARTICLE_TILE_M = 6.0  # a cube of water around the camera; particles farther than 3 m are below a pixel
FISH_TILE_M = 30.0
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
_RANGE_FIELDS = (
    "relief_m", "rocks", "seagrass", "sun_intensity", "sun_elevation_deg", "light_shafts", "shaft_strength",
    "particles", "fish_shoals", "fish_per_shoal", "dolphin_scale", "dolphin_shade",
)  # fmt: skip


@dataclass
class SceneSettings:
    """Scenery switches; simple field types so `services.settings` turns them into ``--scene-*`` flags.

    Every range is [low, high] (drawn uniformly per episode), [x, x] fixes it, [] switches the element off;
    a field left at None takes the preset's range.
    """

    preset: str = "plain"  # plain (the paper's world) | varied (the training ranges); fields set here win
    seabed_textures: list[str] | None = None  # seabed looks drawn from (sand, rippled, gravel, mud, meadow)
    relief_m: list[float] | None = None  # height range of the seabed's mounds, metres
    rocks: list[int] | None = None  # range of the number of rocks on a 40 m seabed tile
    seagrass: list[int] | None = None  # range of the number of seagrass blades on a 40 m tile
    sun_intensity: list[float] | None = None  # sunlight (sun, surface glow, ambient) relative to the plain world's
    sun_elevation_deg: list[float] | None = None  # sun elevation range (the azimuth is uniform)
    light_shafts: list[int] | None = None  # range of the number of light shafts from the surface on a 24 m tile
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
        names = ("seabed_textures", *_RANGE_FIELDS)
        filled = {name: getattr(base, name) if getattr(self, name) is None else getattr(self, name) for name in names}
        resolved = dataclasses.replace(self, **filled)
        _validate(resolved)
        return resolved

    @property
    def plain(self) -> bool:
        """True when every element is off: the episode is the plain world's, pixel for pixel."""
        resolved = self.resolved()
        return resolved.seabed_textures in ([], ["sand"]) and not any(getattr(resolved, n) for n in _RANGE_FIELDS)


def scene_option(value: object) -> SceneSettings | None:
    """A reset's ``scene`` option as `World.reset` takes it: settings from a map, or None (unchanged)."""
    if isinstance(value, dict):
        return SceneSettings.from_mapping(value)
    if value is None or isinstance(value, SceneSettings):
        return value
    raise ValueError(f"'scene' must be a map of scene settings or absent, got {value!r}")


#: Named presets: ``plain`` is the paper's world; ``varied`` holds the training ranges.
PRESETS = {
    "plain": SceneSettings(
        preset="plain", seabed_textures=[], relief_m=[], rocks=[], seagrass=[], sun_intensity=[],
        sun_elevation_deg=[], light_shafts=[], shaft_strength=[], particles=[], fish_shoals=[], fish_per_shoal=[],
        dolphin_scale=[], dolphin_shade=[],
    ),
    "varied": SceneSettings(
        preset="varied", seabed_textures=list(SEABED_TEXTURES), relief_m=[0.5, 2.5], rocks=[0, 8], seagrass=[0, 16],
        sun_intensity=[0.6, 1.3], sun_elevation_deg=[40.0, 90.0], light_shafts=[0, 3], shaft_strength=[0.04, 0.14],
        particles=[5, 25], fish_shoals=[0, 2], fish_per_shoal=[3, 6], dolphin_scale=[0.85, 1.15],
        dolphin_shade=[0.7, 1.25],
    ),
}  # fmt: skip


def _validate(settings: SceneSettings) -> None:
    unknown = set(settings.seabed_textures) - set(SEABED_TEXTURES)
    if unknown:
        raise ValueError(f"unknown seabed textures {sorted(unknown)}; choose from {', '.join(SEABED_TEXTURES)}")
    for name in _RANGE_FIELDS:
        bounds = getattr(settings, name)
        if len(bounds) not in (0, 2) or (bounds and not 0 <= bounds[0] <= bounds[1]):
            raise ValueError(
                f"scene setting {name} must be [] (off) or [low, high] with 0 <= low <= high, got {bounds}"
            )
        most = MAX_FISH_PER_SHOAL if name == "fish_per_shoal" else CAPACITY.get(name)
        if bounds and most is not None and bounds[1] > most:
            raise ValueError(f"scene setting {name} may ask for at most {most}, got {bounds}")


# --- one episode's draw ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Sun:
    intensity: float
    direction: np.ndarray  # unit vector the light travels along (downward)


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
    return EpisodeScene(
        seabed_texture=None if texture in (None, "sand") else texture,
        mounds=mounds if relief else mounds[:0],
        rocks=rocks[: _count(s.rocks, rng)],
        seagrass=seagrass[: _count(s.seagrass, rng)],
        sun=sun,
        shafts=shafts[: _count(s.light_shafts, rng)] if sun is not None else shafts[:0],
        particles=particles[: _count(s.particles, rng)],
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
    direction = -np.array([math.cos(up) * math.cos(azimuth), math.cos(up) * math.sin(azimuth), math.sin(up)])
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


# --- the model's side ----------------------------------------------------------------------------------------------
def build_model(path: Path) -> mujoco.MjModel:
    """The world of ``path`` with the scenery's materials and one mocap body of scenery geoms added after it."""
    spec = mujoco.MjSpec.from_file(str(path))
    for name, look in SEABED_TEXTURES.items():
        if look is not None:
            _textured(spec, f"seabed_{name}", *look)
    _textured(spec, "surface_ripples", (0.55, 0.80, 0.85), (0.95, 1.0, 1.0), 0.3, 30, emission=0.6)
    spec.add_material(name="scene_rock", rgba=[0.33, 0.32, 0.30, 1], specular=0.0)
    spec.add_material(name="scene_mound", rgba=[0.50, 0.48, 0.37, 1], specular=0.0)
    spec.add_material(name="scene_grass", rgba=[0.20, 0.38, 0.16, 1], specular=0.0)
    spec.add_material(name="scene_shaft", rgba=[0.85, 0.95, 0.95, 0.1], emission=1.0, specular=0.0)
    spec.add_material(name="scene_particle", rgba=[0.85, 0.88, 0.85, 1], emission=0.5, specular=0.0)
    spec.add_material(name="scene_fish", rgba=[0.62, 0.66, 0.70, 1], specular=0.5)
    spec.add_mesh(name="scene_fish", uservert=_FISH_VERTICES)
    body = spec.worldbody.add_body(name="scenery", mocap=True)
    box, ellipsoid, mesh = mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_ELLIPSOID, mujoco.mjtGeom.mjGEOM_MESH
    for kind, count, geom_type, material in (
        ("mounds", CAPACITY["mounds"], ellipsoid, "scene_mound"), ("rocks", CAPACITY["rocks"], box, "scene_rock"),
        ("seagrass", CAPACITY["seagrass"], box, "scene_grass"),
        ("light_shafts", CAPACITY["light_shafts"], box, "scene_shaft"),
        ("particles", CAPACITY["particles"], box, "scene_particle"),
        ("fish", CAPACITY["fish_shoals"] * MAX_FISH_PER_SHOAL, mesh, "scene_fish"),
    ):  # fmt: skip
        for index in range(count):
            geom = body.add_geom(name=f"scene_{kind}_{index}", type=geom_type, size=[0.1, 0.1, 0.1], material=material)
            geom.group, geom.contype, geom.conaffinity, geom.density = UNUSED, 0, 0, 0.0
            if geom_type == mesh:
                geom.meshname = "scene_fish"
    model = spec.compile()
    # Each episode moves these geoms within their body: MuJoCo must not take their frames for the body's.
    model.geom_sameframe[model.geom_bodyid == model.body("scenery").id] = 0
    return model


#: A fish as an eight-faced diamond, 40 cm long, 10 cm wide, 16 cm tall: a box's cost, a fish's outline at 64 px.
_FISH_VERTICES = [0.2, 0, 0, -0.2, 0, 0, 0, 0.05, 0, 0, -0.05, 0, 0, 0, 0.08, 0, 0, -0.08]


def _textured(spec, name: str, base, mark, density: float, repeat: int, emission: float = 0.0) -> None:
    spec.add_texture(
        name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT,
        mark=mujoco.mjtMark.mjMARK_RANDOM, random=density, rgb1=list(base), markrgb=list(mark), width=128, height=128,
    )  # fmt: skip
    material = spec.add_material(name=name, texrepeat=[repeat, repeat], specular=0.0, shininess=0.0, emission=emission)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name


class Scenery:
    """Puts an :class:`EpisodeScene` into a model made by :func:`build_model` and keeps it round the rover.

    ``apply`` first puts back everything a scene may change (the sun, the seabed's and surface's materials, the
    dolphin's sizes and colours), so a plain episode after a varied one is the plain world again, bit for bit.
    Every element in use is one row of one table (geom, anchor, velocity, tile), so a step moves them all with a
    handful of array operations.
    """

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.scene = EpisodeScene()
        self.option = mujoco.MjvOption()  # the renderer's scene option: group SHOWN on in varied episodes
        count = {**CAPACITY, "fish": CAPACITY["fish_shoals"] * MAX_FISH_PER_SHOAL}
        kinds = ("mounds", "rocks", "seagrass", "light_shafts", "particles", "fish")
        self._geoms = {
            kind: np.array([model.geom(f"scene_{kind}_{i}").id for i in range(count[kind])], int) for kind in kinds
        }
        self._seabed, self._surface = model.geom("seabed").id, model.geom("surface").id
        self._sun = model.light("sun").id
        dolphin = [model.body(name).id for name in ("dolphin", "dolphin_peduncle", "dolphin_flukes")]
        self._dolphin_geoms = np.flatnonzero(np.isin(model.geom_bodyid, dolphin) & (model.geom_group != 3))
        self._dolphin_materials = [model.material(name).id for name in ("dolphin", "dolphin_dark")]
        self._nominal = self._snapshot()
        self._rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = []  # geoms, anchors, velocities, tile
        self._movers = _Movers.empty()

    @property
    def dolphin_scale(self) -> float:
        return self.scene.dolphin_scale or 1.0

    def apply(self, scene: EpisodeScene, rover_pos: np.ndarray, rover_yaw: float) -> None:
        """Make ``scene`` the episode's, laid out round the rover at ``rover_pos`` facing ``rover_yaw``."""
        self._restore()
        self.scene = scene
        self.option.geomgroup[SHOWN] = not scene.plain
        if scene.plain:
            return
        rover_pos = np.array(rover_pos, float)
        if scene.seabed_texture is not None:
            self.model.geom_matid[self._seabed] = self.model.material(f"seabed_{scene.seabed_texture}").id
        self._lay_seabed(scene, rover_pos)
        if scene.sun is not None:
            self._light(scene.sun, rover_pos)
        particles = self._geoms["particles"][: len(scene.particles)]
        self._show(particles, rover_pos + scene.particles[:, :3], PARTICLE_TILE_M)
        self.model.geom_size[particles] = scene.particles[:, 3:4]
        self._swim_fish(scene, rover_pos, rover_yaw)
        self._dolphin_look(scene)
        self._movers = _Movers.of(self._rows, deep=particles)
        self.follow(rover_pos, 0.0)

    def follow(self, rover_pos: np.ndarray, time: float) -> None:
        """Move the tiles with the rover and the shoals along their course, at sim time ``time``."""
        if self.scene.plain:
            return
        movers = self._movers
        positions = movers.anchors + movers.velocities * time
        positions[:, :2] = _wrapped(positions[:, :2], rover_pos[:2], movers.tiles)
        positions[movers.deep, 2] = _wrapped(positions[movers.deep, 2], rover_pos[2], PARTICLE_TILE_M)
        self.model.geom_pos[movers.geoms] = positions
        if self.scene.sun is not None:
            fade = self.scene.sun.intensity * math.exp(-DEPTH_FALLOFF * (-rover_pos[2] - NOMINAL_DEPTH))
            self.model.vis.headlight.ambient = self._nominal["ambient"] * fade

    # --- internals --------------------------------------------------------------------------------------------
    def _snapshot(self) -> dict[str, np.ndarray]:
        m = self.model
        return {
            "matid": m.geom_matid[[self._seabed, self._surface]].copy(),
            "light_dir": m.light_dir[self._sun].copy(),
            "light_diffuse": m.light_diffuse[self._sun].copy(),
            "ambient": np.array(m.vis.headlight.ambient),
            "dolphin_size": m.geom_size[self._dolphin_geoms].copy(),
            "dolphin_pos": m.geom_pos[self._dolphin_geoms].copy(),
            "dolphin_rgba": m.mat_rgba[self._dolphin_materials].copy(),
        }

    def _restore(self) -> None:
        m, nominal = self.model, self._nominal
        m.geom_matid[[self._seabed, self._surface]] = nominal["matid"]
        m.light_dir[self._sun] = nominal["light_dir"]
        m.light_diffuse[self._sun] = nominal["light_diffuse"]
        m.vis.headlight.ambient = nominal["ambient"]
        m.geom_size[self._dolphin_geoms] = nominal["dolphin_size"]
        m.geom_pos[self._dolphin_geoms] = nominal["dolphin_pos"]
        m.mat_rgba[self._dolphin_materials] = nominal["dolphin_rgba"]
        for geoms in self._geoms.values():
            m.geom_group[geoms] = UNUSED
        self._rows = []
        self._movers = _Movers.empty()

    def _show(self, geoms: np.ndarray, anchors: np.ndarray, tile: float, velocities: np.ndarray | None = None) -> None:
        """Draw ``geoms``, kept at ``anchors`` (world, moving at ``velocities``) on a ``tile`` round the rover."""
        self.model.geom_group[geoms] = SHOWN
        self._rows.append((geoms, anchors, np.zeros_like(anchors) if velocities is None else velocities, tile))

    def _on_seabed(self, kind: str, rows: np.ndarray, rover_pos: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The first ``len(rows)`` geoms of ``kind`` drawn at the rows' places on the seabed tile; their ids."""
        geoms = self._geoms[kind][: len(rows)]
        self._show(geoms, np.column_stack([rover_pos[:2] + rows[:, :2], z]), SEABED_TILE_M)
        return geoms

    def _lay_seabed(self, scene: EpisodeScene, rover_pos: np.ndarray) -> None:
        m = self.model
        mounds = self._on_seabed("mounds", scene.mounds, rover_pos, np.full(len(scene.mounds), SEABED_Z))
        m.geom_size[mounds] = scene.mounds[:, 2:5]
        m.geom_quat[mounds] = _quats(0.0, 0.0, scene.mounds[:, 5])
        rocks = self._on_seabed("rocks", scene.rocks, rover_pos, SEABED_Z + 0.3 * scene.rocks[:, 4])  # set in sand
        m.geom_size[rocks] = scene.rocks[:, 2:5]
        m.geom_quat[rocks] = _quats(scene.rocks[:, 6], scene.rocks[:, 6] / 2, scene.rocks[:, 5])
        height = scene.seagrass[:, 2]
        grass = self._on_seabed("seagrass", scene.seagrass, rover_pos, SEABED_Z + height / 2)
        m.geom_size[grass] = np.column_stack([np.full(len(grass), 0.04), np.full(len(grass), 0.008), height / 2])
        m.geom_quat[grass] = _quats(scene.seagrass[:, 3], scene.seagrass[:, 4], 0.0)

    def _light(self, sun: Sun, rover_pos: np.ndarray) -> None:
        """Sun direction and strength, the surface's ripples glowing with it, and shafts along its rays."""
        m, shafts = self.model, self.scene.shafts
        m.light_dir[self._sun] = sun.direction
        m.light_diffuse[self._sun] = self._nominal["light_diffuse"] * sun.intensity
        ripples = m.material("surface_ripples").id
        m.geom_matid[self._surface] = ripples
        m.mat_emission[ripples] = 0.6 * sun.intensity
        anchors = np.column_stack([rover_pos[:2] + shafts[:, :2], np.full(len(shafts), SEABED_Z / 2)])
        geoms = self._geoms["light_shafts"][: len(shafts)]
        self._show(geoms, anchors, SHAFT_TILE_M)
        half_length = -SEABED_Z / 2 / -sun.direction[2]  # from the surface to the seabed along the rays
        m.geom_size[geoms] = np.column_stack([shafts[:, 2], shafts[:, 2], np.full(len(geoms), half_length)])
        m.geom_quat[geoms] = _z_to(sun.direction)
        if len(geoms):  # one strength an episode, on their shared material
            m.mat_rgba[m.material("scene_shaft").id, 3] = shafts[0, 3]

    def _swim_fish(self, scene: EpisodeScene, rover_pos: np.ndarray, rover_yaw: float) -> None:
        """Shoals start ahead of the rover and swim straight across its view, each fish at its place in the shoal."""
        ahead, aside, depth, across, speed, fish = scene.shoals.T
        forward = np.array([math.cos(rover_yaw), math.sin(rover_yaw)])
        left = np.array([-forward[1], forward[0]])
        heading = rover_yaw + across
        used = [(s, j) for s in range(len(fish)) for j in range(int(fish[s]))]
        shoal = np.array([s for s, _ in used], int)
        centres = np.column_stack(
            [rover_pos[:2] + np.outer(ahead, forward) + np.outer(aside, left), rover_pos[2] + depth]
        )
        offsets = np.array([_yaw_matrix(heading[s]) @ scene.fish_offsets[s, j] for s, j in used]).reshape(-1, 3)
        velocities = np.column_stack([speed * np.cos(heading), speed * np.sin(heading), np.zeros(len(speed))])
        geoms = self._geoms["fish"][[s * MAX_FISH_PER_SHOAL + j for s, j in used]].astype(int)
        self._show(geoms, centres[shoal] + offsets, FISH_TILE_M, velocities[shoal])
        self.model.geom_quat[geoms] = _quats(0.0, 0.0, heading[shoal])

    def _dolphin_look(self, scene: EpisodeScene) -> None:
        m, nominal = self.model, self._nominal
        if scene.dolphin_scale is not None:
            m.geom_size[self._dolphin_geoms] = nominal["dolphin_size"] * scene.dolphin_scale
            m.geom_pos[self._dolphin_geoms] = nominal["dolphin_pos"] * scene.dolphin_scale
        if scene.dolphin_shade is not None:
            rgba = nominal["dolphin_rgba"].copy()
            rgba[:, :3] = np.minimum(rgba[:, :3] * scene.dolphin_shade, 1.0)
            m.mat_rgba[self._dolphin_materials] = rgba


@dataclass(frozen=True)
class _Movers:
    """The table a step moves: each drawn geom's anchor (world), velocity and tile; ``deep`` rows wrap in z too."""

    geoms: np.ndarray
    anchors: np.ndarray
    velocities: np.ndarray
    tiles: np.ndarray  # (n, 1)
    deep: np.ndarray  # bool (n,)

    @classmethod
    def of(cls, rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]], deep: np.ndarray) -> _Movers:
        rows = [(np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), 1.0), *rows]
        geoms = np.concatenate([row[0] for row in rows])
        tiles = np.concatenate([np.full((len(row[0]), 1), row[3]) for row in rows])
        anchors, velocities = (np.concatenate([row[i] for row in rows]) for i in (1, 2))
        return cls(geoms, anchors, velocities, tiles, np.isin(geoms, deep))

    @classmethod
    def empty(cls) -> _Movers:
        return cls.of([], np.zeros(0, int))


def _wrapped(anchors: np.ndarray, centre: np.ndarray, tile: float) -> np.ndarray:
    """Each anchor moved by whole tiles to lie within half a tile of ``centre`` on every axis."""
    return centre + np.mod(anchors - centre + tile / 2, tile) - tile / 2


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _quats(roll, pitch, yaw) -> np.ndarray:
    """Quaternions (n, 4) of rotations by roll, pitch, yaw (arrays of one length, or numbers) about x, y, z."""
    angles = np.column_stack(np.broadcast_arrays(roll, pitch, yaw)).reshape(-1, 3)
    quats = np.zeros((len(angles), 4))
    for quat, euler in zip(quats, angles, strict=True):
        mujoco.mju_euler2Quat(quat, euler, "xyz")
    return quats


def _z_to(direction: np.ndarray) -> np.ndarray:
    """The rotation taking the z axis onto ``direction``."""
    quat = np.zeros(4)
    mujoco.mju_quatZ2Vec(quat, np.asarray(direction, float))
    return quat
