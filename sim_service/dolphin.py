"""The target: a bottlenose dolphin swimming toward wandering waypoints.

The dolphin is kinematic: its motion is scripted here and written into
MuJoCo mocap bodies each step, so it pushes the rover on contact but is never
pushed back, as in the reference simulator. Everything random comes from the
episode's generator, so a seed fixes the whole swim.

Behaviour (numbers from the SPEC where it gives them):
* forward speed drawn once per episode in ``speed_range`` (the SPEC gives
  none; we keep it below the rover's 1.5 m/s top speed so tracking is possible);
* turns toward the current waypoint at no more than ``max_turn_deg_per_step``
  (1.3 deg per 0.02 s step, about 65 deg/s), easing its turn rate so banking
  looks smooth; a waypoint is redrawn within +-10 m of the rover on arrival;
* banks into turns (roll proportional to turn rate) and undulates: body pitch
  and two tail joints (peduncle, flukes) oscillate with a phase lag.

That is the ``planar`` motion, the paper's and the default: the dolphin stays at
the depth it was placed at. The ``3d`` motion (:class:`DolphinSettings`) adds a
depth to each waypoint, drawn within a depth band, pitches the dolphin into
climbs and dives toward it at a limited pitch and pitch rate, and sends it up
to breathe every minute or two (docs/physics.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim_service.rotations import clamp, euler_to_matrix, matrix_to_quat
from sim_service.settings import DolphinSettings, Motion

#: Pivot offsets along the body's -x axis (metres), matching assets/world.xml.
TAIL_PIVOT = 0.78  # body centre -> peduncle joint
FLUKE_PIVOT = 0.42  # peduncle joint -> fluke joint


@dataclass(frozen=True)
class DolphinParams:
    speed_range: tuple[float, float] = (0.5, 1.0)  # m/s
    max_turn_deg_per_step: float = 1.3
    turn_gain: float = 0.05  # deg/step of turn rate per degree of heading error
    turn_easing_deg_per_step: float = 0.1  # largest change of turn rate per step
    waypoint_radius: float = 10.0  # waypoints within +-radius of the rover, per horizontal axis
    arrival_radius: float = 1.5
    bank_deg_at_max_turn: float = 30.0
    beat_hz_per_mps: float = 1.6  # tail beat frequency per unit of speed
    body_pitch_deg: float = 3.0
    peduncle_deg: float = 18.0
    fluke_deg: float = 30.0
    fluke_lag_rad: float = 1.2
    # The 3d motion's depth band, for the body's centre (z up, surface at 0): at the ceiling its back and blowhole
    # break the surface; the floor keeps the 0.88 m tall body clear of the varied seabed (relief up to -9.5 m).
    ceiling_z: float = -0.3
    floor_z: float = -8.0
    waypoint_z_range: tuple[float, float] = (-8.0, -1.0)  # depths of ordinary waypoints
    # Issue 46's figure for bottlenose climbs and dives, about 30 to 45 degrees of pitch: we take 40, so at 0.5 to
    # 1 m/s it climbs or dives at up to 0.32 to 0.64 m/s.
    max_climb_deg: float = 40.0
    climb_gain_deg_per_m: float = 10.0  # wished climb angle per metre of depth still to go
    max_climb_rate_deg_per_step: float = 0.4  # 20 deg/s: climbs and dives start and level off over about 2 s
    surfacing_interval_s: tuple[float, float] = (50.0, 100.0)  # breath to heading up again: with the climb, 1-2 min
    surfacing_aim_above_m: float = 1.0  # aims this far above the ceiling, so it arrives climbing, not creeping up


@dataclass
class DolphinState:
    position: np.ndarray  # world, m
    yaw: float  # rad
    speed: float  # m/s
    turn_rate: float  # deg per step, + = counter-clockwise seen from above
    phase: float  # tail-beat phase in cycles, [0, 1)
    waypoint: np.ndarray  # world (x, y)
    waypoint_z: float = 0.0  # the waypoint's depth (3d motion)
    climb: float = 0.0  # rad, the swim's angle above the horizontal (3d motion; the body pitches nose-up by it)
    surfacing_in_s: float = math.inf  # time until it heads up to breathe; <= 0 while it does (3d motion)


@dataclass(frozen=True)
class PartPose:
    """World pose of one mocap body of the dolphin."""

    position: np.ndarray
    rotation: np.ndarray  # 3x3 body-to-world

    @property
    def quat(self) -> np.ndarray:
        return matrix_to_quat(self.rotation)


class DolphinBehaviour:
    def __init__(self, params: DolphinParams | None = None, motion: Motion = "planar") -> None:
        DolphinSettings(motion).check()
        self.params = params or DolphinParams()
        self.three_d = motion == "3d"
        self.state: DolphinState | None = None

    def reset(
        self,
        rng: np.random.Generator,
        position: np.ndarray,
        yaw: float,
        turn_rate: float,
        phase: float,
        rover_xy: np.ndarray,
    ) -> None:
        speed = float(rng.uniform(*self.params.speed_range))
        self.state = DolphinState(
            np.array(position, dtype=float), float(yaw), speed, float(turn_rate), float(phase) % 1.0, np.zeros(2)
        )
        self._new_waypoint(rng, rover_xy)
        if self.three_d:
            self._draw_next_surfacing(rng)

    def _new_waypoint(self, rng: np.random.Generator, rover_xy: np.ndarray) -> None:
        r = self.params.waypoint_radius
        self.state.waypoint = np.asarray(rover_xy[:2], dtype=float) + rng.uniform(-r, r, size=2)
        if self.three_d:  # drawn after (x, y), so the planar motion's draws stay as they were
            self.state.waypoint_z = float(rng.uniform(*self.params.waypoint_z_range))

    def _draw_next_surfacing(self, rng: np.random.Generator) -> None:
        self.state.surfacing_in_s = float(rng.uniform(*self.params.surfacing_interval_s))

    def step(self, dt: float, rng: np.random.Generator, rover_xy: np.ndarray) -> None:
        p, s = self.params, self.state
        to_waypoint = s.waypoint - s.position[:2]
        if math.hypot(to_waypoint[0], to_waypoint[1]) < p.arrival_radius:
            self._new_waypoint(rng, rover_xy)
            to_waypoint = s.waypoint - s.position[:2]
        heading_error = math.degrees(_wrap(math.atan2(to_waypoint[1], to_waypoint[0]) - s.yaw))
        wish = clamp(p.turn_gain * heading_error, -p.max_turn_deg_per_step, p.max_turn_deg_per_step)
        ease = p.turn_easing_deg_per_step
        eased = s.turn_rate + clamp(wish - s.turn_rate, -ease, ease)
        s.turn_rate = clamp(eased, -p.max_turn_deg_per_step, p.max_turn_deg_per_step)
        s.yaw = _wrap(s.yaw + math.radians(s.turn_rate))
        if self.three_d:
            s.surfacing_in_s -= dt
            self._pitch_toward(self._target_z())
        s.position[:2] += s.speed * math.cos(s.climb) * dt * np.array([math.cos(s.yaw), math.sin(s.yaw)])
        if self.three_d:
            self._change_depth(dt, rng)
        s.phase = (s.phase + p.beat_hz_per_mps * s.speed * dt) % 1.0

    @property
    def surfacing(self) -> bool:
        """Whether the dolphin is heading up to breathe (3d motion)."""
        return self.state.surfacing_in_s <= 0

    def _target_z(self) -> float:
        p = self.params
        return p.ceiling_z + p.surfacing_aim_above_m if self.surfacing else self.state.waypoint_z

    def _pitch_toward(self, target_z: float) -> None:
        """Turn the climb angle toward one proportional to the depth still to go, within the pitch and its rate."""
        p, s = self.params, self.state
        wish = clamp(p.climb_gain_deg_per_m * (target_z - s.position[2]), -p.max_climb_deg, p.max_climb_deg)
        rate = p.max_climb_rate_deg_per_step
        s.climb += math.radians(clamp(wish - math.degrees(s.climb), -rate, rate))

    def _change_depth(self, dt: float, rng: np.random.Generator) -> None:
        """Climb or dive along the swim's angle, kept in the depth band; a breath at the ceiling ends a surfacing."""
        p, s = self.params, self.state
        s.position[2] = clamp(s.position[2] + s.speed * math.sin(s.climb) * dt, p.floor_z, p.ceiling_z)
        if self.surfacing and s.position[2] >= p.ceiling_z:
            self._draw_next_surfacing(rng)

    @property
    def forward(self) -> np.ndarray:
        s = self.state
        horizontal = math.cos(s.climb)
        return np.array([horizontal * math.cos(s.yaw), horizontal * math.sin(s.yaw), math.sin(s.climb)])

    @property
    def velocity(self) -> np.ndarray:
        return self.state.speed * self.forward

    def body_rotation(self) -> np.ndarray:
        p, s = self.params, self.state
        roll = -math.radians(p.bank_deg_at_max_turn) * s.turn_rate / p.max_turn_deg_per_step
        pitch = math.radians(p.body_pitch_deg) * math.sin(2 * math.pi * s.phase) - s.climb  # + pitch: nose down
        return euler_to_matrix(roll, pitch, s.yaw)

    def part_poses(self) -> tuple[PartPose, PartPose, PartPose]:
        """(body, peduncle, flukes): each tail part pitches about its pivot, lagging the one before."""
        p, s = self.params, self.state
        beat = 2 * math.pi * s.phase
        body = PartPose(s.position.copy(), self.body_rotation())
        peduncle_rot = body.rotation @ euler_to_matrix(0.0, math.radians(p.peduncle_deg) * math.sin(beat), 0.0)
        peduncle_pos = body.position + body.rotation @ np.array([-TAIL_PIVOT, 0.0, 0.0])
        fluke_angle = math.radians(p.fluke_deg) * math.sin(beat - p.fluke_lag_rad)
        fluke_rot = peduncle_rot @ euler_to_matrix(0.0, fluke_angle, 0.0)
        fluke_pos = peduncle_pos + peduncle_rot @ np.array([-FLUKE_PIVOT, 0.0, 0.0])
        return body, PartPose(peduncle_pos, peduncle_rot), PartPose(fluke_pos, fluke_rot)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi
