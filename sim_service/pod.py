"""The target's companions: the other dolphins of a pod, swimming beside it.

A companion is kinematic like the target and follows the target's swim: its place is an offset in the target's
frame (along its heading, to its left, and up) that drifts toward a goal redrawn every few seconds, so companions
fall behind, overtake and cross from one side of the target to the other, now and then between the rover and the
target. Each has its own tail-beat phase and rate, size and shade. Every draw comes from the pod's own generator
(a child of the episode's seed), so the target's swim and the rover's draws are the same whatever the pod size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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

    def __init__(self, size: int, params: PodParams | None = None) -> None:
        self.size = size  # dolphins, the target included
        self.params = params or PodParams()
        self.companions: list[Companion] = []
        self.rng = np.random.default_rng(0)
        self._poser = DolphinBehaviour()  # poses each companion's state as the target's own are posed

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
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

    def step(self, dt: float, target: DolphinBehaviour) -> None:
        p = self.params
        for companion in self.companions:
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

    def part_poses(self, target: DolphinBehaviour) -> list[tuple[PartPose, PartPose, PartPose]]:
        """Each companion's (body, peduncle, flukes), swum as the target is, at its offset and heading."""
        t, p = target.state, target.params
        self._poser.params = p
        cos, sin = math.cos(t.yaw), math.sin(t.yaw)
        poses = []
        for companion in self.companions:
            along, left, up = companion.offset
            position = t.position + np.array([cos * along - sin * left, sin * along + cos * left, up])
            if target.three_d:  # companions keep to the target's depth band
                position[2] = clamp(position[2], p.floor_z, p.ceiling_z)
            # Drifting sideways turns it a little off the target's heading, toward where it goes.
            yaw = t.yaw + math.atan2(companion.drift[1], t.speed + companion.drift[0])
            self._poser.state = DolphinState(
                position, yaw, t.speed, t.turn_rate, companion.phase, t.waypoint, climb=t.climb
            )
            poses.append(self._poser.part_poses())
        return poses
