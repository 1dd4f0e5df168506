"""Is the dolphin's azimuth in the silhouette's centre? One camera-only 3d episode's every third frame (seed 211, as
shift_average.py), each frame's dolphin segmented from the water (its colour's distance from its row's median
colour above a threshold; the connected part nearest the column the CMVAE reads), the azimuth of that part's
contrast-weighted centre column set against the true azimuth and the CMVAE's read.

    MUJOCO_GL=egl python docs/eval_report/selection/3d/silhouette_centroid.py encoder_service/models/cmvae_vertical.pt
"""

import sys

import cv2
import numpy as np
from shift_average import loop_frames

from encoder_service.inference import LatentEncoder
from encoder_service.train import focal_length_px

THRESHOLDS = (10, 20, 30)  # colour distance (0-255 RGB units) that counts as dolphin


def silhouette_azimuths(frames: np.ndarray, read: np.ndarray, threshold: float) -> np.ndarray:
    """Each frame's silhouette-centre azimuth (degrees, + = left); the CMVAE's read where nothing stands out."""
    focal_px, half = focal_length_px(frames.shape[2]), frames.shape[2] / 2
    pixels = frames.astype(np.float32)
    contrast = np.linalg.norm(pixels - np.median(pixels, axis=2, keepdims=True), axis=3)
    azimuths = read.copy()
    for i, frame_contrast in enumerate(contrast):
        count, labels, _, centres = cv2.connectedComponentsWithStats((frame_contrast > threshold).astype(np.uint8))
        if count <= 1:
            continue
        read_column = half - focal_px * np.tan(np.radians(read[i]))
        part = 1 + int(np.argmin(np.abs(centres[1:, 0] - read_column)))
        weights = np.where(labels == part, frame_contrast, 0.0).sum(axis=0)
        column = (weights * (np.arange(len(weights)) + 0.5)).sum() / weights.sum()
        azimuths[i] = np.degrees(np.arctan((half - column) / focal_px))
    return azimuths


def main() -> None:
    encoder = LatentEncoder(sys.argv[1])
    frames, azimuths = loop_frames(encoder)
    read = np.stack(encoder.decode_state(encoder.encode(frames)[0]))[1]
    print(f"CMVAE: theta MAE {abs(read - azimuths).mean():.3f} deg, bias {(read - azimuths).mean():+.3f} "
          f"({len(frames)} frames)")  # fmt: skip
    for threshold in THRESHOLDS:
        error = silhouette_azimuths(frames, read, threshold) - azimuths
        print(f"silhouette centre, threshold {threshold}: theta MAE {abs(error).mean():.3f} deg, "
              f"bias {error.mean():+.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
