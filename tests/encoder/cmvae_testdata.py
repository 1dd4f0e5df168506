"""A small on-disk CMVAE dataset in the `swimm dataset` format, drawn with NumPy, for the encoder tests.

Why not the real sim: these tests exercise the reader, trainer and
evaluator, not the renderer, and must stay fast on two CPU cores. The
frames still carry their labels, so the networks have something to learn:
a disc sits left or right with the signed azimuth theta, shrinks with the
distance d, and its colour follows the target yaw psi.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.geometry import ALPHA_DEG

POSE_NAMES = [f"{body}_{axis}" for body in ("rover", "target") for axis in ("x", "y", "z", "roll", "pitch", "yaw")]


def draw_frames(labels: np.ndarray) -> np.ndarray:
    """One 64x64 RGB frame per (d, theta, psi) row."""
    rows, cols = np.mgrid[0:64, 0:64]
    frames = np.empty((len(labels), 64, 64, 3), dtype=np.uint8)
    frames[:] = np.array([20, 60, 110], dtype=np.uint8)  # water
    for frame, (d, theta, psi) in zip(frames, labels, strict=True):
        centre_x = 32.0 - 28.0 * theta / ALPHA_DEG  # positive azimuth = target to the left
        radius = 60.0 / d
        disc = (cols - centre_x) ** 2 + (rows - 32.0) ** 2 <= radius**2
        shade = 0.5 + 0.5 * np.cos(np.radians(psi))
        frame[disc] = np.array([200 * shade + 40, 180, 240 - 200 * shade], dtype=np.uint8)
    return frames


def poses_of(labels: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rover and target poses (degrees) that put the target at each row's d and azimuth from the rover's centre."""
    poses = np.zeros((len(labels), 12), dtype=np.float32)
    poses[:, 0:2] = rng.uniform(-30, 30, (len(labels), 2))
    poses[:, 5] = rng.uniform(-180, 180, len(labels))
    bearing = np.radians(poses[:, 5] + labels[:, 1])
    poses[:, 6] = poses[:, 0] + labels[:, 0] * np.cos(bearing)
    poses[:, 7] = poses[:, 1] + labels[:, 0] * np.sin(bearing)
    poses[:, 11] = poses[:, 5] + labels[:, 2]
    return poses


def write_dataset(root: Path, count: int, seed: int, shard_size: int, noise: float = 0.0) -> Path:
    """Write ``count`` frames in shards of ``shard_size``; ``noise`` > 0 adds Gaussian pixel noise (same poses)."""
    rng = np.random.default_rng(seed)
    labels = np.stack(
        [rng.uniform(2, 10, count), rng.uniform(-ALPHA_DEG, ALPHA_DEG, count), rng.uniform(-180, 180, count)], axis=1
    ).astype(np.float32)
    poses = poses_of(labels, rng)
    frames = draw_frames(labels)
    if noise > 0:
        jitter = np.random.default_rng(seed + 1).normal(0.0, noise, frames.shape)
        frames = np.clip(frames + jitter, 0, 255).astype(np.uint8)
    root.mkdir(parents=True, exist_ok=True)
    shards = []
    for number, start in enumerate(range(0, count, shard_size)):
        name = f"shard-{number:05d}"
        part = slice(start, start + shard_size)
        np.save(root / f"{name}.images.npy", frames[part])
        np.save(root / f"{name}.labels.npy", labels[part])
        np.save(root / f"{name}.poses.npy", poses[part])
        shards.append(name)
    meta = {
        "format": "swimm-cmvae-dataset",
        "version": 1,
        "count": count,
        "seed": seed,
        "image_shape": [64, 64, 3],
        "shard_size": shard_size,
        "label_names": ["d", "theta", "psi"],
        "pose_names": POSE_NAMES,
        "shards": shards,
    }
    (root / "meta.json").write_text(json.dumps(meta))
    return root
