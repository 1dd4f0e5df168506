"""The target's companions: the other dolphins of a pod, swimming beside it.

A companion is kinematic like the target and follows the target's swim: its place is an offset in the target's
frame (along its heading, to its left, and up) that drifts toward a goal redrawn every few seconds, so companions
fall behind, overtake and cross from one side of the target to the other, now and then between the rover and the
target. Each has its own tail-beat phase and rate, size and shade. Every draw comes from the pod's own generator
(a child of the episode's seed), so the target's swim and the rover's draws are the same whatever the pod size.

The target is the dolphin the camera is centred on when tracking starts: at the first frame every companion is
redrawn until it is farther off the camera's axis than the target and does not hide it (:meth:`Pod.centre_target`).
With ``crossing`` (the crossing split), the first companion is no free swimmer: it sways across the line of sight,
halfway between the rover and the target, on a fixed schedule (:meth:`Pod.step`). A dataset's sample puts it there
at a drawn moment of such a crossing instead (:meth:`Pod.put_on_sight`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.identity import off_axis_deg, target_occluded
from sim_service.dolphin import DolphinBehaviour, DolphinState, PartPose
from sim_service.rotations import clamp


@dataclass(frozen=True)
class PodParams:
    along_m: tuple[float, float] = (-3.0, 3.0)  # offsets ahead (+) of or behind the target
    left_m: tuple[float, float] = (-4.0, 4.0)  # offsets to the target's left (+) or right
    up_m: tuple[float, float] = (-0.6, 0.6)
    clearance_m: tuple[float, float] = (2.6, 1.0)  # half axes (along, left) of the ellipse kept clear round the target
    goal_interval_s: tuple[float, float] = (4.0, 12.0)  # how long a companion keeps its goal offset
    drift_gain: float = 0.3  # per second: the wished drift speed per metre still to go
    max_drift_mps: float = 0.4  # relative to the target
    drift_accel: float = 0.1  # m/s^2: drifts start and end smoothly
    beat_factor: tuple[float, float] = (0.85, 1.15)  # on the target's tail-beat rate per speed
    scale: tuple[float, float] = (0.9, 1.1)  # drawn size
    shade: tuple[float, float] = (0.8, 1.2)  # factor on the grey
    centred_margin_deg: float = 5.0  # at the first frame every companion is this much farther off the camera's axis
    centring_draws: int = 20  # offsets drawn for a companion too near the axis; the farthest off it if none clears
    crossing_side_m: float = 3.0  # the crossing companion sways this far to either side of the line of sight
    crossing_period_s: float = 20.0  # there and back: it crosses the line of sight every half period
    #: A companion put on the line of sight (a dataset's sample) is at most this far to its side, so that it hides
    #: part of the target (their girth discs overlap as the camera sees them).
    sight_sway_m: float = 0.5


@dataclass
class Companion:
    offset: np.ndarray  # (along, left, up) in the target's heading frame, m
    drift: np.ndarray  # the offset's rate of change, m/s
    goal: np.ndarray  # the offset it drifts toward
    goal_in_s: float  # time until the next goal
    phase: float  # tail-beat phase in cycles
    beat_factor: float
    scale: float
    shade: float


class Pod:
    """The companions of one episode; :meth:`reset` draws them, :meth:`step` moves them after the target's step."""

    def __init__(self, size: int, crossing: bool = False, params: PodParams | None = None) -> None:
        self.size = size  # dolphins, the target included
        self.crossing = crossing
        self.params = params or PodParams()
        self.companions: list[Companion] = []
        self.rng = np.random.default_rng(0)
        self.time_s = 0.0
        self._crossing_side = 1.0  # +1: the crossing companion starts left of the line of sight (seen from the rover)
        self._poser = DolphinBehaviour()  # poses each companion's state as the target's own are posed

    def reset(
        self, rng: np.random.Generator, target: DolphinBehaviour, rover_position: np.ndarray, crossing_side: float = 1.0
    ) -> None:
        """Draw the companions round ``target``; a crossing companion starts on ``crossing_side`` (+1 left) of the
        line of sight, which the caller picks away from the camera's axis so the target stays the centred one."""
        self.rng = rng
        self.time_s = 0.0
        self._crossing_side = crossing_side
        p = self.params
        self.companions = []
        for _ in range(self.size - 1):
            offset = self._draw_offset()
            # goal_in_s 0: its first step draws its first goal.
            companion = Companion(
                offset=offset, drift=np.zeros(3), goal=offset.copy(), goal_in_s=0.0, phase=rng.uniform(0.0, 1.0),
                beat_factor=rng.uniform(*p.beat_factor), scale=rng.uniform(*p.scale), shade=rng.uniform(*p.shade),
            )  # fmt: skip
            self.companions.append(companion)
        if self.crossing:
            self.crosser.offset = self._sight_offset(target, rover_position, self._crossing_sway())

    @property
    def crosser(self) -> Companion:
        """The companion that crosses the line of sight (the first), when the pod is built with ``crossing``."""
        return self.companions[0]

    def centre_target(self, target: DolphinBehaviour, in_camera: Callable[[np.ndarray], np.ndarray]) -> None:
        """Redraw each free companion nearer the camera's axis than the target (plus the margin), or hiding it.

        ``in_camera`` turns world positions (N, 3) into the camera's (forward, left, up) frame. Draws come from the
        pod's generator, so the same seed redraws the same companions the same way.
        """
        target_point = in_camera(target.state.position[None])[0]
        limit = float(off_axis_deg(target_point[None])[0]) + self.params.centred_margin_deg

        def clearance(offset: np.ndarray) -> float:
            """How far beyond the limit off the axis a companion at ``offset`` is; -inf when it hides the target."""
            point = in_camera(self.position(offset, target)[None])[0]
            hides = target_occluded(np.stack([target_point, point]))
            return -math.inf if hides else float(off_axis_deg(point[None])[0]) - limit

        for companion in self.companions[1:] if self.crossing else self.companions:
            if clearance(companion.offset) >= 0:
                continue
            drawn = [self._draw_offset() for _ in range(self.params.centring_draws)]
            companion.offset = next((o for o in drawn if clearance(o) >= 0), max(drawn, key=clearance))
            companion.goal = companion.offset.copy()

    def _draw_offset(self) -> np.ndarray:
        p = self.params
        offset = np.array([self.rng.uniform(*p.along_m), self.rng.uniform(*p.left_m), self.rng.uniform(*p.up_m)])
        return self._kept_clear(offset)

    def _kept_clear(self, offset: np.ndarray) -> np.ndarray:
        """``offset`` moved out onto the ellipse round the target when inside it: companions pass it, not through it."""
        reach = math.hypot(*(offset[:2] / self.params.clearance_m))
        if 0 < reach < 1:
            offset[:2] /= reach
        return offset

    def _new_goal(self, companion: Companion) -> None:
        companion.goal = self._draw_offset()
        companion.goal_in_s = float(self.rng.uniform(*self.params.goal_interval_s))

    def step(self, dt: float, target: DolphinBehaviour, rover_position: np.ndarray) -> None:
        p = self.params
        self.time_s += dt
        free = self.companions
        if self.crossing:
            self._cross(dt, target, rover_position)
            free = self.companions[1:]
        for companion in free:
            companion.goal_in_s -= dt
            if companion.goal_in_s <= 0:
                self._new_goal(companion)
            wish = p.drift_gain * (companion.goal - companion.offset)
            wish *= min(1.0, p.max_drift_mps / max(float(np.linalg.norm(wish)), 1e-9))
            change = wish - companion.drift
            companion.drift += change * min(1.0, p.drift_accel * dt / max(float(np.linalg.norm(change)), 1e-9))
            companion.offset = self._kept_clear(companion.offset + companion.drift * dt)
            speed = target.state.speed + companion.drift[0]
            beat = target.params.beat_hz_per_mps * companion.beat_factor * speed * dt
            companion.phase = (companion.phase + beat) % 1.0

    def _cross(self, dt: float, target: DolphinBehaviour, rover_position: np.ndarray) -> None:
        """Move the crossing companion along its sway; its drift is its motion seen from the target, for its pose."""
        crosser = self.crosser
        offset = self._sight_offset(target, rover_position, self._crossing_sway())
        crosser.drift = (offset - crosser.offset) / dt
        crosser.offset = offset
        speed = target.state.speed + crosser.drift[0]
        crosser.phase = (crosser.phase + target.params.beat_hz_per_mps * crosser.beat_factor * speed * dt) % 1.0

    def _crossing_sway(self) -> float:
        """How far left of the line of sight the crossing companion is now: it crosses the line at a quarter period,
        then every half period (a cosine, so it eases at either side)."""
        p = self.params
        return self._crossing_side * p.crossing_side_m * math.cos(2 * math.pi * self.time_s / p.crossing_period_s)

    def put_on_sight(self, rng: np.random.Generator, target: DolphinBehaviour, rover_position: np.ndarray) -> None:
        """Put the first companion halfway between the rover and the target, hiding part of it: a moment of a crossing
        (datasets' samples); the sway to the side of the line of sight is drawn from ``rng``."""
        sway = rng.uniform(-self.params.sight_sway_m, self.params.sight_sway_m)
        first = self.companions[0]
        first.offset = self._sight_offset(target, rover_position, sway)
        first.goal = first.offset.copy()

    def _sight_offset(self, target: DolphinBehaviour, rover_position: np.ndarray, sway: float) -> np.ndarray:
        """Halfway from the target to the rover, ``sway`` m to the left of the line of sight (seen from the rover)."""
        t = target.state
        sight = t.position - rover_position
        left_of_sight = np.array([-sight[1], sight[0], 0.0]) / max(math.hypot(sight[0], sight[1]), 1e-9)
        away = -0.5 * sight + sway * left_of_sight  # from the target, in the world frame
        cos, sin = math.cos(t.yaw), math.sin(t.yaw)
        return np.array([cos * away[0] + sin * away[1], -sin * away[0] + cos * away[1], away[2]])

    def position(self, offset: np.ndarray, target: DolphinBehaviour) -> np.ndarray:
        """The world position of a companion at ``offset`` from ``target``."""
        t, p = target.state, target.params
        cos, sin = math.cos(t.yaw), math.sin(t.yaw)
        along, left, up = offset
        position = t.position + np.array([cos * along - sin * left, sin * along + cos * left, up])
        if target.three_d:  # companions keep to the target's depth band
            position[2] = clamp(position[2], p.floor_z, p.ceiling_z)
        return position

    def part_poses(self, target: DolphinBehaviour) -> list[tuple[PartPose, PartPose, PartPose]]:
        """Each companion's (body, peduncle, flukes), swum as the target is, at its offset and heading."""
        t, p = target.state, target.params
        self._poser.params = p
        poses = []
        for companion in self.companions:
            position = self.position(companion.offset, target)
            # Drifting sideways turns it a little off the target's heading, toward where it goes.
            yaw = t.yaw + math.atan2(companion.drift[1], t.speed + companion.drift[0])
            self._poser.state = DolphinState(
                position, yaw, t.speed, t.turn_rate, companion.phase, t.waypoint, climb=t.climb
            )
            poses.append(self._poser.part_poses())
        return poses
