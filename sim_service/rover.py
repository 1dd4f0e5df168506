"""BlueROV2 dynamics that MuJoCo does not provide: thrusters, buoyancy, water drag, dive modes.

MuJoCo integrates the rigid body (mass, inertia, gravity, added mass as joint
armature, see ``assets/world.xml``); this module computes every other force
once per physics step and returns it as one world-frame wrench to apply at
the centre of mass. It is plain numpy so it can be tested without a model.

Parameters (SI units) are the published BlueROV2 Fossen model of Wu (2018),
"6-DoF Modelling and Control of a Remotely Operated Vehicle", Flinders
University, the source family the SPEC cites: weight 112.8 N, buoyancy
114.8 N, centre of buoyancy 0.02 m above the centre of gravity, linear and
quadratic damping per axis.

Thrust limit: a T200 at 16 V gives about 5.1 kgf forward; ArduSub's default
pilot gain of 50 % maps full stick to 1500 +- 200 us, where the T200 curve
gives about 1.9 kgf forward and 1.5 kgf reverse. We use the mean, 16.6 N, for
every thruster in both directions, which keeps the mixer symmetric. With
Wu's surge damping that yields a full-surge terminal speed of 1.50 m/s,
the BlueROV2's rated top speed (see docs/physics.md for the check).

Frames: world z up; body x forward, y left, z up. Commands follow ArduSub's
sign conventions: surge + forward, sway + right, heave + up, yaw + turns the
nose left (counter-clockwise seen from above).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from services.messages import DiveMode
from sim_service.rotations import clamp

GRAVITY = 9.81


@dataclass(frozen=True)
class RoverParams:
    mass: float = 11.5  # kg, so weight = 112.8 N
    buoyancy: float = 114.8  # N: slightly positive, as a trimmed BlueROV2
    cob_above_cog: float = 0.02  # m: gives the passive roll/pitch restoring moment
    linear_damping: tuple[float, ...] = (4.03, 6.22, 5.18, 0.07, 0.07, 0.07)  # X Y Z K M N
    quadratic_damping: tuple[float, ...] = (18.18, 21.66, 36.99, 1.55, 1.55, 1.55)
    max_thrust: float = 16.6  # N per thruster, see the module docstring
    # Horizontal thrusters: (x, y) position and thrust direction angle in the body frame (vectored layout).
    horizontal: tuple[tuple[float, float, float], ...] = (
        (0.156, -0.111, np.deg2rad(45.0)),  # front right
        (0.156, 0.111, np.deg2rad(-45.0)),  # front left
        (-0.156, -0.111, np.deg2rad(-45.0)),  # rear right
        (-0.156, 0.111, np.deg2rad(45.0)),  # rear left
    )
    vertical_y: float = 0.111  # the two vertical thrusters sit at y = +-vertical_y, pushing along z


@dataclass(frozen=True)
class ControllerGains:
    """ArduSub-like inner loops for the stabilise and depth_hold modes."""

    roll_kp: float = 8.0  # N m / rad
    roll_kd: float = 1.5  # N m / (rad/s)
    depth_kp: float = 60.0  # N / m
    depth_kd: float = 40.0  # N / (m/s)
    depth_ki: float = 10.0  # N / (m s)
    max_climb_rate: float = 0.5  # m/s of depth change at full heave stick in depth_hold


def _allocation(params: RoverParams) -> np.ndarray:
    """Rows (Fx, Fy, Mz): the body wrench per newton of each horizontal thruster."""
    columns = []
    for x, y, angle in params.horizontal:
        fx, fy = np.cos(angle), np.sin(angle)
        columns.append((fx, fy, x * fy - y * fx))
    return np.array(columns).T


@dataclass
class RoverDynamics:
    """Turns (sway, heave, surge, yaw) commands and the rover's state into a world-frame wrench."""

    params: RoverParams = field(default_factory=RoverParams)
    gains: ControllerGains = field(default_factory=ControllerGains)

    def __post_init__(self) -> None:
        self._alloc = _allocation(self.params)
        self._linear_damping = np.array(self.params.linear_damping)
        self._quadratic_damping = np.array(self.params.quadratic_damping)
        self._alloc_pinv = np.linalg.pinv(self._alloc)
        # Full authority per axis: the wrench when every thruster pushes that axis at its limit.
        self._axis_max = np.abs(self._alloc).sum(axis=1) * self.params.max_thrust
        self.reset(depth=0.0)

    def reset(self, depth: float) -> None:
        self.depth_setpoint = depth
        # Start trimmed: the integrator already cancels the known net buoyancy, so depth holds from step one.
        net_up = self.params.buoyancy - self.params.mass * GRAVITY
        self._depth_integral = -net_up / self.gains.depth_ki

    def horizontal_thrusts(self, surge: float, sway: float, yaw: float) -> np.ndarray:
        """Per-thruster forces (N) for normalised commands, scaled down together when any saturates."""
        wish = np.array([surge, -sway, yaw]) * self._axis_max  # sway + is to the right, body y is left
        thrusts = self._alloc_pinv @ wish
        peak = np.abs(thrusts).max()
        if peak > self.params.max_thrust:
            thrusts *= self.params.max_thrust / peak
        return thrusts

    def wrench(
        self,
        command: tuple[float, float, float, float],
        mode: DiveMode,
        rotation: np.ndarray,
        position: np.ndarray,
        lin_vel: np.ndarray,
        ang_vel: np.ndarray,
        dt: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """World-frame (force, torque about the centre of mass) for one step.

        ``rotation`` is the body-to-world matrix; velocities are world-frame.
        """
        sway, heave, surge, yaw = command
        p = self.params
        lin_b = rotation.T @ lin_vel
        ang_b = rotation.T @ ang_vel

        horizontal = self.horizontal_thrusts(surge, sway, yaw)
        fx, fy, mz = self._alloc @ horizontal
        heave_force, roll_torque = self._vertical(heave, mode, rotation, position, lin_vel, ang_b, dt)
        force_b = np.array([fx, fy, heave_force])
        torque_b = np.array([roll_torque, 0.0, mz])

        velocity_b = np.concatenate([lin_b, ang_b])
        drag = -(self._linear_damping + self._quadratic_damping * np.abs(velocity_b)) * velocity_b
        force_b += drag[:3]
        torque_b += drag[3:]

        # Buoyancy acts straight up at the centre of buoyancy, cob_above_cog along the body's z axis: its
        # moment is lever x (0, 0, B), written out (np.cross costs more than the rest of the wrench).
        lever_x, lever_y = rotation[0, 2] * p.cob_above_cog, rotation[1, 2] * p.cob_above_cog
        force_w = rotation @ force_b
        force_w[2] += p.buoyancy
        torque_w = rotation @ torque_b
        torque_w[0] += lever_y * p.buoyancy
        torque_w[1] -= lever_x * p.buoyancy
        return force_w, torque_w

    def _vertical(
        self,
        heave: float,
        mode: DiveMode,
        rotation: np.ndarray,
        position: np.ndarray,
        lin_vel: np.ndarray,
        ang_b: np.ndarray,
        dt: float,
    ) -> tuple[float, float]:
        """Heave force and roll torque of the two vertical thrusters, limited to what they can give."""
        g = self.gains
        limit = 2 * self.params.max_thrust
        if mode == DiveMode.DEPTH_HOLD:
            self.depth_setpoint += heave * g.max_climb_rate * dt
            error = self.depth_setpoint - position[2]
            self._depth_integral += error * dt
            heave_force = g.depth_kp * error - g.depth_kd * lin_vel[2] + g.depth_ki * self._depth_integral
        else:
            self.depth_setpoint = position[2]
            heave_force = heave * limit
        roll_torque = 0.0
        if mode in (DiveMode.DEPTH_HOLD, DiveMode.STABILISE):
            roll = math.atan2(rotation[2, 1], rotation[2, 2])
            roll_torque = -g.roll_kp * roll - g.roll_kd * ang_b[0]
        # Split into the two thrusters and saturate each, as the hardware would.
        arm = self.params.vertical_y
        per_thruster = self.params.max_thrust
        left = clamp(float(heave_force / 2 + roll_torque / (2 * arm)), -per_thruster, per_thruster)
        right = clamp(float(heave_force / 2 - roll_torque / (2 * arm)), -per_thruster, per_thruster)
        return float(left + right), float((left - right) * arm)
