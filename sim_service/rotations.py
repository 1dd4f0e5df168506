"""Small rotation helpers, so the world's kinematics read as maths rather than as MuJoCo calls."""

from __future__ import annotations

import math

import mujoco
import numpy as np


def euler_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body-to-world rotation for intrinsic z-y-x (yaw, then pitch, then roll) angles in radians."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion of a rotation matrix, w >= 0 (MuJoCo's convention).

    MuJoCo's C routine: the world calls this four times a step, where numpy's small-array overhead showed.
    """
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation, dtype=float).reshape(9))
    return -quat if quat[0] < 0 else quat


def clamp(value: float, low: float, high: float) -> float:
    """``value`` limited to [low, high], for scalars (np.clip's array machinery costs microseconds per call)."""
    return low if value < low else high if value > high else value
