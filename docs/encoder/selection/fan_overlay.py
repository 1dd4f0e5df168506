"""Does a fan of pale rays drawn over the training scenery's frames mislead a CMVAE as the low sun's shafts do?

Reset frames of the selection seed (211) in the training scenery (``wide``, no noise), read as they are and with
each image-space overlay of encoder_service/augment.py drawn on all of them, beside the low-sun split's own reset
frames of the same seed; prints and writes d and theta errors per overlay and model (docs/encoder.md, "A low
sun's shafts in perspective").

    MUJOCO_GL=egl python docs/encoder/selection/fan_overlay.py OUT.csv CHECKPOINT [CHECKPOINT ...]
"""

import sys
from pathlib import Path

import numpy as np
from detector_frames import condition_frames
from low_sun_ablation import SEED, write_table

from encoder_service.augment import bands, fans, shafts
from encoder_service.inference import LatentEncoder
from sim_service.scenery import PRESETS
from sim_service.settings import WorldSettings
from sim_service.splits import SPLITS, Split
from sim_service.world import World

FRAMES = 300
EDGE_DEG = 15.0  # a dolphin this far off the axis or more is "near the edge", where the shafts' misreads are
OVERLAYS = {"none": None, "fans": fans, "shafts": shafts, "bands": bands}


def errors(encoder: LatentEncoder, frames: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    d, theta, _ = encoder.decode_state(encoder.encode(frames)[0])
    theta_error = np.abs(theta - labels[:, 1])
    edge = np.abs(labels[:, 1]) >= EDGE_DEG
    return {"d_mae_m": round(float(np.abs(d - labels[:, 0]).mean()), 3),
            "d_bias_m": round(float(np.mean(d - labels[:, 0])), 3),
            "theta_mae_deg": round(float(theta_error.mean()), 2),
            "edge_theta_mae_deg": round(float(theta_error[edge].mean()), 2),
            "share_over_10_deg": round(float(np.mean(theta_error > 10.0)), 3)}  # fmt: skip


def main(out: str, checkpoints: list[str]) -> None:
    world = World(WorldSettings())
    frames, labels = condition_frames(world, Split("wide", "the training scenery", scene=PRESETS["wide"]), SEED, FRAMES)
    low_sun = condition_frames(world, SPLITS["low-sun"], SEED, FRAMES)
    world.close()
    inputs = {name: frames if draw is None else draw(frames, np.random.default_rng(SEED), 1.0)
              for name, draw in OVERLAYS.items()}  # fmt: skip
    rows = []
    for checkpoint in checkpoints:
        encoder, model = LatentEncoder(checkpoint), Path(checkpoint).name
        for name, images in inputs.items():
            frames_read = "wide" if name == "none" else f"wide + {name}"
            rows.append({"checkpoint": model, "frames": frames_read, **errors(encoder, images, labels)})
        rows.append({"checkpoint": model, "frames": "low-sun split", **errors(encoder, *low_sun)})
    write_table(out, rows, checkpoints)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
