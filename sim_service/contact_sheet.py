"""A contact sheet of camera frames: the same reset poses rendered clean and noisy, side by side.

    python -m sim_service.contact_sheet --out docs/frames.png --count 8 --seed 11

Row one shows clean 64x64 frames, row two the same poses with
:data:`~sim_service.noise.NOISY_PRESET`; each frame is upscaled (nearest
neighbour, so the pixels the encoder sees stay visible) and captioned with
the target's distance and azimuth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from services.geometry import relative_geometry
from sim_service.world import World

UPSCALE = 3
CAPTION_PX = 14


def frames(count: int, seed: int, noise: bool) -> tuple[list[np.ndarray], list[str]]:
    """``count`` reset frames of seeds ``seed, seed+1, ...`` and their captions."""
    world = World()
    images, captions = [], []
    try:
        for offset in range(count):
            telemetry, image = world.reset(seed + offset, noise=noise)
            images.append(image)
            where = relative_geometry(telemetry)
            captions.append(f"{where.d:.1f}m {where.azimuth:+.0f}deg")
    finally:
        world.close()
    return images, captions


def tile(image: np.ndarray, caption: str) -> np.ndarray:
    big = cv2.resize(image, None, fx=UPSCALE, fy=UPSCALE, interpolation=cv2.INTER_NEAREST)
    band = np.full((CAPTION_PX, big.shape[1], 3), 255, np.uint8)
    cv2.putText(band, caption, (2, CAPTION_PX - 4), cv2.FONT_HERSHEY_PLAIN, 0.75, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([big, band])


def contact_sheet(count: int, seed: int) -> np.ndarray:
    rows = []
    for noise in (False, True):
        images, captions = frames(count, seed, noise)
        rows.append(np.hstack([tile(image, caption) for image, caption in zip(images, captions, strict=True)]))
    return np.vstack(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/frames.png")
    parser.add_argument("--count", type=int, default=8)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    sheet = contact_sheet(args.count, args.seed)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main()
