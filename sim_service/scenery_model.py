"""The varied world's MuJoCo side: the scenery's geoms and materials, and an episode's scene put into them.

Cheap on a software renderer: every element is a box, three flat ellipsoids (the mounds) or an eight-faced
mesh (a fish), all attached to one mocap body added after the world's own bodies, so the world's ids do not
move. They live in geom group :data:`SHOWN` while in use and :data:`UNUSED` otherwise; the renderer shows group
:data:`SHOWN` only in a varied episode, so a plain episode draws exactly the frames the plain world always drew.
The seabed, the particles, the light shafts and the shoals are laid out on tiles that wrap around the rover
(each element jumps by a tile when it falls more than half a tile behind), so the rover never leaves them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from sim_service.scenery import (
    CAPACITY,
    DEPTH_FALLOFF,
    FISH_TILE_M,
    MAX_FISH_PER_SHOAL,
    NOMINAL_DEPTH,
    PARTICLE_TILE_M,
    SEABED_TEXTURES,
    SEABED_TILE_M,
    SEABED_Z,
    SHAFT_TILE_M,
    EpisodeScene,
    Sun,
)

SHOWN, UNUSED = 4, 5  # geom groups: drawn in a varied episode / never drawn
DOLPHIN_PARTS = ("dolphin", "dolphin_peduncle", "dolphin_flukes")  # the target's mocap bodies
DOLPHIN_MATERIALS = ("dolphin", "dolphin_dark")  # the greys a shade multiplies


def part_names(index: int) -> tuple[str, ...]:
    """The mocap bodies of dolphin ``index`` of the pod: 0 is the target, 1 on its companions."""
    return DOLPHIN_PARTS if index == 0 else tuple(f"{name}_{index}" for name in DOLPHIN_PARTS)


def build_model(path: Path, companions: int = 0) -> mujoco.MjModel:
    """The world of ``path`` with the scenery's materials and one mocap body of scenery geoms added after it.

    ``companions`` more dolphins follow, after everything else so no other id moves, each a copy of the
    target's drawn geoms (no collider) with greys of its own.
    """
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
    if companions:
        _add_companions(spec, mujoco.MjModel.from_xml_path(str(path)), companions)
    model = spec.compile()
    # Each episode moves these geoms within their body: MuJoCo must not take their frames for the body's.
    model.geom_sameframe[model.geom_bodyid == model.body("scenery").id] = 0
    return model


#: A fish as an eight-faced diamond, 40 cm long, 10 cm wide, 16 cm tall: a box's cost, a fish's outline at 64 px.
_FISH_VERTICES = [0.2, 0, 0, -0.2, 0, 0, 0, 0.05, 0, 0, -0.05, 0, 0, 0, 0.08, 0, 0, -0.08]


def _add_companions(spec, reference: mujoco.MjModel, count: int) -> None:
    """Copy the target's drawn geoms, as ``reference`` compiled them, onto ``count`` companions' mocap bodies."""
    for index in range(1, count + 1):
        for name in DOLPHIN_MATERIALS:
            grey = spec.material(name)
            spec.add_material(name=f"{name}_{index}", rgba=grey.rgba, specular=grey.specular, shininess=grey.shininess)
        for part, name in zip(DOLPHIN_PARTS, part_names(index), strict=True):
            body = spec.worldbody.add_body(name=name, mocap=True)
            for geom in _drawn_geoms(reference, [reference.body(part).id]):
                material = reference.material(reference.geom_matid[geom]).name
                body.add_geom(
                    type=mujoco.mjtGeom(reference.geom_type[geom]), size=reference.geom_size[geom],
                    pos=reference.geom_pos[geom], quat=reference.geom_quat[geom], contype=0, conaffinity=0,
                    material=f"{material}_{index}" if material in DOLPHIN_MATERIALS else material,
                )  # fmt: skip


def _drawn_geoms(model: mujoco.MjModel, bodies: list[int]) -> np.ndarray:
    """The geoms of ``bodies`` that are drawn: all but the collider (group 3)."""
    return np.flatnonzero(np.isin(model.geom_bodyid, bodies) & (model.geom_group != 3))


def _textured(spec, name: str, base, mark, density: float, repeat: int, emission: float = 0.0) -> None:
    spec.add_texture(
        name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT,
        mark=mujoco.mjtMark.mjMARK_RANDOM, random=density, rgb1=list(base), markrgb=list(mark), width=128, height=128,
    )  # fmt: skip
    material = spec.add_material(name=name, texrepeat=[repeat, repeat], specular=0.0, shininess=0.0, emission=emission)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name


class PodLooks:
    """Gives each companion of a model made by :func:`build_model` its episode's size and shade."""

    def __init__(self, model: mujoco.MjModel, companions: int) -> None:
        self.model = model
        self._geoms = [
            _drawn_geoms(model, [model.body(name).id for name in part_names(i)]) for i in range(1, companions + 1)
        ]
        self._materials = [
            [model.material(f"{name}_{i}").id for name in DOLPHIN_MATERIALS] for i in range(1, companions + 1)
        ]
        if companions:  # every companion is built from the same nominal geoms and greys
            self._size, self._pos = model.geom_size[self._geoms[0]].copy(), model.geom_pos[self._geoms[0]].copy()
            self._rgba = model.mat_rgba[self._materials[0]].copy()

    def dress(self, index: int, scale: float, shade: float) -> None:
        """Companion ``index`` (1 on) drawn at ``scale`` times the nominal size, its greys times ``shade``."""
        geoms, m = self._geoms[index - 1], self.model
        m.geom_size[geoms], m.geom_pos[geoms] = self._size * scale, self._pos * scale
        rgba = self._rgba.copy()
        rgba[:, :3] = np.minimum(rgba[:, :3] * shade, 1.0)
        m.mat_rgba[self._materials[index - 1]] = rgba


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
        self._varied = False
        self.option = mujoco.MjvOption()  # the renderer's scene option: group SHOWN on in varied episodes
        count = {**CAPACITY, "fish": CAPACITY["fish_shoals"] * MAX_FISH_PER_SHOAL}
        kinds = ("mounds", "rocks", "seagrass", "light_shafts", "particles", "fish")
        self._geoms = {
            kind: np.array([model.geom(f"scene_{kind}_{i}").id for i in range(count[kind])], int) for kind in kinds
        }
        self._seabed, self._surface = model.geom("seabed").id, model.geom("surface").id
        self._sun = model.light("sun").id
        self._dolphin_geoms = _drawn_geoms(model, [model.body(name).id for name in DOLPHIN_PARTS])
        self._dolphin_materials = [model.material(name).id for name in DOLPHIN_MATERIALS]
        self._nominal = self._snapshot()
        self._rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = []  # geoms, anchors, velocities, tile
        self._movers = _Movers.empty()
        self._geom_pos, self._geom_group = model.geom_pos, model.geom_group  # views, fetched once for the steps

    @property
    def dolphin_scale(self) -> float:
        return self.scene.dolphin_scale or 1.0

    def apply(self, scene: EpisodeScene, rover_pos: np.ndarray, rover_yaw: float) -> None:
        """Make ``scene`` the episode's, laid out round the rover at ``rover_pos`` facing ``rover_yaw``."""
        self._restore()
        self.scene = scene
        self._varied = not scene.plain
        self.option.geomgroup[SHOWN] = self._varied
        if not self._varied:
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
        radii = np.maximum(np.linalg.norm(self.model.geom_size, axis=1), self.model.geom_rbound)
        self._movers = _Movers.of(self._rows, deep=particles, radii=radii)
        self.follow(rover_pos, rover_yaw, 0.0)

    def follow(self, rover_pos: np.ndarray, rover_yaw: float, time: float) -> None:
        """Move the tiles with the rover and the shoals along their course, at sim time ``time``.

        What lies wholly outside the 100 degree wedge ahead of the rover is left out of the drawing: a geom costs
        the software renderer about as much drawn off screen as on it. The camera sees 80 degrees across, up to 93
        at its corners when the rover rolls; the wedge holds that with room for a few degrees of pitch.
        """
        if not self._varied:
            return
        movers = self._movers
        if len(movers.geoms):
            positions = movers.anchors + movers.velocities * time
            positions -= movers.wraps * np.floor((positions - rover_pos) / movers.tiles + 0.5)
            self._geom_pos[movers.geoms] = positions
            ahead, aside = ((positions[:, :2] - rover_pos[:2]) @ _heading_frame(rover_yaw)).T
            seen = (ahead > -movers.radii) & (np.abs(aside) - _WEDGE_SLOPE * ahead < _WEDGE_MARGIN * movers.radii)
            self._geom_group[movers.geoms] = np.where(seen, SHOWN, UNUSED)
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
    """The table a step moves: each drawn geom's anchor (world), velocity and tile size per axis.

    A geom is moved by whole tiles to lie within half a tile of the rover on each axis that wraps (x and y; z too
    for the ``deep`` rows, the particles): ``wraps`` is the tile on those axes and 0 on the others.
    """

    geoms: np.ndarray
    anchors: np.ndarray
    velocities: np.ndarray
    tiles: np.ndarray  # (n, 3), 1 on an axis that does not wrap
    wraps: np.ndarray  # (n, 3)
    radii: np.ndarray  # (n,) bounding radius of each geom

    @classmethod
    def of(
        cls, rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]], deep: np.ndarray, radii: np.ndarray
    ) -> _Movers:
        rows = [(np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), 1.0), *rows]
        geoms = np.concatenate([row[0] for row in rows])
        anchors, velocities = (np.concatenate([row[i] for row in rows]) for i in (1, 2))
        tiles = np.concatenate([np.full((len(row[0]), 3), row[3]) for row in rows])
        tiles[~np.isin(geoms, deep), 2] = 1.0
        wraps = tiles.copy()
        wraps[~np.isin(geoms, deep), 2] = 0.0
        return cls(geoms, anchors, velocities, tiles, wraps, radii[geoms])

    @classmethod
    def empty(cls) -> _Movers:
        return cls.of([], np.zeros(0, int), np.zeros(0))


_WEDGE_SLOPE = 1.2  # tan(50 degrees): the wedge's half-width per metre ahead
_WEDGE_MARGIN = 1.6  # > sqrt(1 + 1.2^2): a geom's radius measured across the wedge's edge, with room to spare


def _heading_frame(yaw: float) -> np.ndarray:
    """Columns: the rover's forward and left directions in the horizontal plane (offsets @ it: ahead, aside)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


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
