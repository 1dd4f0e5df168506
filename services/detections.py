"""A pod detector's output read as dolphins: heatmap peaks to bearings and distances, in numpy only.

The detector (encoder_service.pod_detector) gives, per frame, a heat map of dolphin centres on a coarse grid and at
each cell the sub-cell offset and the log of that dolphin's distance. Reading its peaks is shared by the encoder
service (torch or onnxruntime underneath) and by `swimm pilot`, which runs an exported detector without torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.geometry import ALPHA_DEG, BETA_DEG, CAMERA_AHEAD_M

TAN_ALPHA = math.tan(math.radians(ALPHA_DEG))
TAN_BETA = math.tan(math.radians(BETA_DEG))


@dataclass(frozen=True)
class Detections:
    """One frame's dolphins, strongest first: score in (0, 1), azimuth and elevation in degrees (+ = left, above),
    distance in metres."""

    score: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.score)


def from_pixels(x: np.ndarray, y: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Image (x, y) in pixels -> (azimuth, elevation) in degrees of the ray through them."""
    left = (1.0 - 2.0 * np.asarray(x) / size) * TAN_ALPHA
    up = (1.0 - 2.0 * np.asarray(y) / size) * TAN_BETA
    return np.degrees(np.arctan(left)), np.degrees(np.arctan2(up, np.hypot(1.0, left)))


def rover_azimuth(camera_azimuth: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """The task's azimuth (from the rover's centre, degrees) of a dolphin the camera, :data:`CAMERA_AHEAD_M` ahead
    of that centre, sees at ``camera_azimuth`` degrees, ``distance`` metres from the rover's centre."""
    alpha = np.radians(camera_azimuth)
    sin, cos = np.sin(alpha), np.cos(alpha)
    from_camera = -CAMERA_AHEAD_M * cos + np.sqrt(np.maximum(distance**2 - (CAMERA_AHEAD_M * sin) ** 2, 0.0))
    return np.degrees(np.arctan2(from_camera * sin, from_camera * cos + CAMERA_AHEAD_M))


def local_maxima(heat: np.ndarray) -> np.ndarray:
    """Cells of ``heat`` (N, G, G) at least as high as their 3x3 neighbourhood (a max pool's peaks)."""
    grid = heat.shape[-1]
    padded = np.pad(heat, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    around = np.max([padded[:, dy : dy + grid, dx : dx + grid] for dy in range(3) for dx in range(3)], axis=0)
    return heat == around


def read_peaks(heat: np.ndarray, regression: np.ndarray, threshold: float, size: int, stride: int) -> list[Detections]:
    """Each frame's :class:`Detections` from the detector's heat (N, G, G), scores in (0, 1), and regression
    (N, 3, G, G): the 3x3 local maxima above ``threshold``, placed by their offsets and distances."""
    peaks = local_maxima(heat) & (heat > threshold)
    frames = []
    for n in range(len(heat)):
        iy, ix = np.nonzero(peaks[n])
        order = np.argsort(-heat[n, iy, ix], kind="stable")
        iy, ix = iy[order], ix[order]
        r = regression[n][:, iy, ix]
        azimuth, elevation = from_pixels((ix + r[0]) * stride, (iy + r[1]) * stride, size)
        distance = np.exp(r[2])
        frames.append(Detections(heat[n, iy, ix], rover_azimuth(azimuth, distance), elevation, distance))
    return frames
