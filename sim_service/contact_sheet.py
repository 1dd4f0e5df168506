"""A contact sheet of camera frames: the same reset poses rendered clean and noisy, or plain and varied.

    python -m sim_service.contact_sheet --out docs/frames.png --count 8 --seed 11
    python -m sim_service.contact_sheet --out docs/frames_varied.png --count 6 --seed 11 --scene varied --pairs 3

Row one shows clean 64x64 frames, row two the same poses with
:data:`~sim_service.noise.NOISY_PRESET`. With ``--scene``, each pair of rows
shows the plain world and the same poses in the named scenery preset
(sim_service/scenery.py), the next pair the next seeds. Each frame is upscaled
(nearest neighbour, so the pixels the encoder sees stay visible) and captioned
with the target's distance and azimuth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from services.geometry import relative_geometry
from services.process import DEFAULT_RENDER_THREADS, ProcessSettings, configure_process
from sim_service.scenery import SceneSettings
from sim_service.world import World

UPSCALE = 3
CAPTION_PX = 14


def frames(count: int, seed: int, noise: bool, scene: str = "plain") -> tuple[list[np.ndarray], list[str]]:
    """``count`` reset frames of seeds ``seed, seed+1, ...`` in the ``scene`` preset, and their captions."""
    world = World()
    images, captions = [], []
    try:
        for offset in range(count):
            telemetry, image = world.reset(seed + offset, noise=noise, scene=SceneSettings(preset=scene))
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


def row(images: list[np.ndarray], captions: list[str]) -> np.ndarray:
    return np.hstack([tile(image, caption) for image, caption in zip(images, captions, strict=True)])


def contact_sheet(count: int, seed: int) -> np.ndarray:
    return np.vstack([row(*frames(count, seed, noise)) for noise in (False, True)])


def scenery_sheet(count: int, seed: int, scene: str, pairs: int) -> np.ndarray:
    """``pairs`` pairs of rows: ``count`` clean plain frames over the same poses in the ``scene`` preset."""
    rows = []
    for pair in range(pairs):
        first = seed + pair * count
        rows += [row(*frames(count, first, False, preset)) for preset in ("plain", scene)]
    return np.vstack(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/frames.png")
    parser.add_argument("--count", type=int, default=8)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--scene", default="", help="a scenery preset: plain rows over rows in it, not noise")
    parser.add_argument("--pairs", type=int, default=2, help="with --scene: pairs of rows, each on new seeds")
    args = parser.parse_args()
    configure_process(ProcessSettings(render_threads=DEFAULT_RENDER_THREADS), role="contact sheet")  # LP_NUM_THREADS
    sheet = (
        scenery_sheet(args.count, args.seed, args.scene, args.pairs)
        if args.scene
        else contact_sheet(args.count, args.seed)
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main()
