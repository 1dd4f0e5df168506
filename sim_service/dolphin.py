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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim_service.rotations import clamp, euler_to_matrix, matrix_to_quat

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


@dataclass
class DolphinState:
    position: np.ndarray  # world, m
    yaw: float  # rad
    speed: float  # m/s
    turn_rate: float  # deg per step, + = counter-clockwise seen from above
    phase: float  # tail-beat phase in cycles, [0, 1)
    waypoint: np.ndarray  # world (x, y)


@dataclass(frozen=True)
class PartPose:
    """World pose of one mocap body of the dolphin."""

    position: np.ndarray
    rotation: np.ndarray  # 3x3 body-to-world

    @property
    def quat(self) -> np.ndarray:
        return matrix_to_quat(self.rotation)


class DolphinBehaviour:
    def __init__(self, params: DolphinParams | None = None) -> None:
        self.params = params or DolphinParams()
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

    def _new_waypoint(self, rng: np.random.Generator, rover_xy: np.ndarray) -> None:
        r = self.params.waypoint_radius
        self.state.waypoint = np.asarray(rover_xy[:2], dtype=float) + rng.uniform(-r, r, size=2)

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
        s.position[:2] += s.speed * dt * np.array([math.cos(s.yaw), math.sin(s.yaw)])
        s.phase = (s.phase + p.beat_hz_per_mps * s.speed * dt) % 1.0

    @property
    def forward(self) -> np.ndarray:
        return np.array([math.cos(self.state.yaw), math.sin(self.state.yaw), 0.0])

    @property
    def velocity(self) -> np.ndarray:
        return self.state.speed * self.forward

    def body_rotation(self) -> np.ndarray:
        p, s = self.params, self.state
        roll = -math.radians(p.bank_deg_at_max_turn) * s.turn_rate / p.max_turn_deg_per_step
        pitch = math.radians(p.body_pitch_deg) * math.sin(2 * math.pi * s.phase)
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
