"""The task's relative quantities d, theta and psi, defined once for every service.

The sim labels datasets with them, the learner's task rewards with them and
the evaluator measures with them, so they live in the shared core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.telemetry import Telemetry

#: Horizontal field of view of the IMX322 camera (SPEC: 2*atan(4.98 / (2*2.97))).
CAMERA_FOCAL_MM = 2.97
CAMERA_SENSOR_MM = (4.98, 3.74)
HFOV_DEG = math.degrees(2 * math.atan(CAMERA_SENSOR_MM[0] / (2 * CAMERA_FOCAL_MM)))
VFOV_DEG = math.degrees(2 * math.atan(CAMERA_SENSOR_MM[1] / (2 * CAMERA_FOCAL_MM)))
#: alpha: half the horizontal field of view, the largest azimuth that keeps the target in view.
ALPHA_DEG = HFOV_DEG / 2
#: beta: half the vertical field of view, the largest elevation that keeps the target in view (the 3d task).
BETA_DEG = VFOV_DEG / 2
#: What a CMVAE dataset labels each frame with (`swimm dataset`): the planar task's d m, signed azimuth deg and
#: psi deg, and for the 3d task's frames (`--vertical`) the signed elevation deg too.
LABEL_NAMES = ("d", "theta", "psi")
VERTICAL_LABEL_NAMES = (*LABEL_NAMES, "elevation")

OPT_D = 6.0
MAX_D = 4.0
#: The nose camera sits this far ahead of the rover's centre (sim_service/assets: camera "nose"), where the SPEC
#: measures d and theta from.
CAMERA_AHEAD_M = 0.235
#: ... and this far above it; it is mounted level, looking along the rover's forward axis (no tilt).
CAMERA_ABOVE_M = 0.02


@dataclass(frozen=True)
class RelativeGeometry:
    d: float  # horizontal distance rover -> target, m
    theta: float  # unsigned azimuth error, degrees in [0, 180]
    azimuth: float  # signed azimuth, degrees in (-180, 180], positive = target to the rover's left
    psi: float  # target yaw relative to the rover, degrees in (-180, 180]


@dataclass(frozen=True)
class VerticalGeometry:
    """What the 3d task adds to :class:`RelativeGeometry`."""

    distance: float  # 3d distance rover -> target, m (d is its horizontal part)
    elevation: float  # signed elevation in the camera's frame, degrees in [-90, 90], positive = target above
    phi: float  # unsigned elevation error, degrees in [0, 90]


def quat_to_euler(quat) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of a (w, x, y, z) quaternion: the inverse of the sim's ``euler_to_matrix``.

    It lives in the shared core because the learner's state observation needs it where MuJoCo is not installed.
    """
    w, x, y, z = quat
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def yaw_of(forward: tuple[float, float, float]) -> float:
    """Heading in degrees of a forward vector projected on the horizontal plane."""
    return math.degrees(math.atan2(forward[1], forward[0]))


def wrap_deg(angle: float) -> float:
    """Wrap an angle in degrees to (-180, 180]."""
    wrapped = math.fmod(angle + 180.0, 360.0)
    if wrapped <= 0:
        wrapped += 360.0
    return wrapped - 180.0


def relative_geometry(t: Telemetry) -> RelativeGeometry:
    hx = t.target_pos[0] - t.rover_pos[0]
    hy = t.target_pos[1] - t.rover_pos[1]
    d = math.hypot(hx, hy)
    rover_yaw = yaw_of(t.rover_forward)
    bearing = math.degrees(math.atan2(hy, hx)) if d > 0 else rover_yaw
    azimuth = wrap_deg(bearing - rover_yaw)
    psi = wrap_deg(yaw_of(t.target_forward) - rover_yaw)
    return RelativeGeometry(d=d, theta=abs(azimuth), azimuth=azimuth, psi=psi)


def rotate_into_body(quat, vector) -> tuple[float, float, float]:
    """``vector`` (world frame) in the frame of the body whose orientation is the (w, x, y, z) ``quat``."""
    w, x, y, z = quat
    vx, vy, vz = vector
    # Rotation by the conjugate quaternion, written out: t = 2 (v x u), v' = v + w t - u x t, with u = (x, y, z).
    tx, ty, tz = 2 * (z * vy - y * vz), 2 * (x * vz - z * vx), 2 * (y * vx - x * vy)
    return (
        vx + w * tx - (y * tz - z * ty),
        vy + w * ty - (z * tx - x * tz),
        vz + w * tz - (x * ty - y * tx),
    )


def vertical_geometry(t: Telemetry) -> VerticalGeometry:
    """The target's 3d distance from the rover and its elevation seen from the camera.

    The distance is measured from the rover's centre, like d; the elevation from the camera, in its own frame
    (level, looking along the rover's forward axis), so a pitching rover tilts the view as the picture does.
    Elevation is the spherical one, the angle above the camera's horizontal plane: the vertical counterpart of
    the azimuth, which is the angle within that plane.
    """
    offset = tuple(target - rover for target, rover in zip(t.target_pos, t.rover_pos, strict=True))
    ahead, left, up = rotate_into_body(t.rover_quat, offset)
    ahead, up = ahead - CAMERA_AHEAD_M, up - CAMERA_ABOVE_M
    elevation = math.degrees(math.atan2(up, math.hypot(ahead, left)))
    return VerticalGeometry(distance=math.dist(t.target_pos, t.rover_pos), elevation=elevation, phi=abs(elevation))


def camera_centred(rover_xy, rover_yaw_deg, target_xy) -> tuple:
    """(d, signed azimuth in degrees) of the target seen from the camera rather than the rover's centre.

    Vectorised: arrays of rover positions (N, 2), headings (N,) and target positions (N, 2) give arrays.
    """
    import numpy as np  # the core's other functions need no numpy

    yaw = np.radians(np.asarray(rover_yaw_deg, dtype=float))
    forward = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    h = np.asarray(target_xy, dtype=float) - (np.asarray(rover_xy, dtype=float) + CAMERA_AHEAD_M * forward)
    ahead = (forward * h).sum(axis=-1)
    left = forward[..., 0] * h[..., 1] - forward[..., 1] * h[..., 0]
    return np.hypot(h[..., 0], h[..., 1]), np.degrees(np.arctan2(left, ahead))
