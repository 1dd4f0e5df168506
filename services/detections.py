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
LOOK_RADIUS = 2  # a 5x5 window about a dolphin's centre...
LOOK_PIXELS = 5  # ...whose lightest few are its back, a pixel or two off the centre as the detector places it


@dataclass(frozen=True)
class Detections:
    """One frame's dolphins, strongest first: score in (0, 1), azimuth and elevation in degrees (+ = left, above),
    distance in metres, and how light each looks against the water (:func:`pixel_looks`; NaN where not read)."""

    score: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray
    distance: np.ndarray
    look: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.look is None:
            object.__setattr__(self, "look", np.full(len(self.score), np.nan))

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


def pixel_looks(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """How light the dolphins centred at pixels (x, y) look in ``image`` (H, W, 3) uint8: the mean grey of the 5
    lightest pixels of the 5x5 window about each centre, less the frame's median grey (the water's brightness).

    The lightest pixels, not the window's mean, so that a centre read a pixel off still reads the animal's back."""
    grey = image.astype(np.float32).mean(axis=2)
    padded = np.pad(grey, LOOK_RADIUS, mode="edge")
    h, w = grey.shape
    cx = np.clip(np.round(x).astype(int), 0, w - 1)
    cy = np.clip(np.round(y).astype(int), 0, h - 1)
    side = 2 * LOOK_RADIUS + 1
    windows = np.stack([padded[cy + dy, cx + dx] for dy in range(side) for dx in range(side)])
    return np.sort(windows, axis=0)[-LOOK_PIXELS:].mean(axis=0) - np.median(grey)


def read_peaks(
    heat: np.ndarray, regression: np.ndarray, threshold: float, size: int, stride: int, images: np.ndarray | None = None
) -> list[Detections]:
    """Each frame's :class:`Detections` from the detector's heat (N, G, G), scores in (0, 1), and regression
    (N, 3, G, G): the 3x3 local maxima above ``threshold``, placed by their offsets and distances; given the frames
    (N, H, W, 3), each detection's look is read from its pixels (:func:`pixel_looks`)."""
    peaks = local_maxima(heat) & (heat > threshold)
    frames = []
    for n in range(len(heat)):
        iy, ix = np.nonzero(peaks[n])
        order = np.argsort(-heat[n, iy, ix], kind="stable")
        iy, ix = iy[order], ix[order]
        r = regression[n][:, iy, ix]
        x, y = (ix + r[0]) * stride, (iy + r[1]) * stride
        azimuth, elevation = from_pixels(x, y, size)
        distance = np.exp(r[2])
        look = None if images is None else pixel_looks(images[n], x, y)
        frames.append(Detections(heat[n, iy, ix], rover_azimuth(azimuth, distance), elevation, distance, look))
    return frames
