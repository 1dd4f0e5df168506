"""Which part of the low-sun split misleads a CMVAE: the dim sun, its low elevation, or the light shafts?

The split's scenery with one group of its ranges put back to the training ones, 150 reset frames each on the
selection seed (211); prints and writes d and theta MAE per variant and model (docs/encoder.md, "Light shafts").

    MUJOCO_GL=egl python docs/encoder/selection/low_sun_ablation.py OUT.csv CHECKPOINT [CHECKPOINT ...]
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from detector_frames import condition_frames

from encoder_service.inference import LatentEncoder
from encoder_service.model import label_errors
from services.results import provenance, write_provenance_beside
from sim_service.scenery import PRESETS
from sim_service.settings import WorldSettings
from sim_service.splits import SPLITS, Split
from sim_service.world import World

FRAMES, SEED = 150, 211
TRAINING = PRESETS["varied"]
VARIANTS = {
    "low-sun": {},
    "no shafts": {"light_shafts": [0, 0]},
    "training sun, split's shafts": {"sun_intensity": TRAINING.sun_intensity,
                                     "sun_elevation_deg": TRAINING.sun_elevation_deg},
    "split's sun, training shafts": {"light_shafts": TRAINING.light_shafts, "shaft_strength": TRAINING.shaft_strength},
    "split's sun and shaft count, training strength": {"shaft_strength": TRAINING.shaft_strength},
}  # fmt: skip


def main(out: str, checkpoints: list[str]) -> None:
    world = World(WorldSettings())
    rows = []
    for checkpoint in checkpoints:
        encoder = LatentEncoder(checkpoint)
        for name, ranges in VARIANTS.items():
            scene = dataclasses.replace(SPLITS["low-sun"].scene, **ranges)
            frames, labels = condition_frames(world, Split(name, "", scene=scene), SEED, FRAMES)
            mu, _ = encoder.encode(frames)
            d_error, theta_error, _ = label_errors(np.stack(encoder.decode_state(mu), axis=1), labels).mean(0)
            rows.append({"checkpoint": Path(checkpoint).name, "variant": name, "frames": FRAMES,
                         "d_mae_m": round(float(d_error), 3),
                         "theta_mae_deg": round(float(theta_error), 2)})  # fmt: skip
    world.close()
    write_table(out, rows, checkpoints)


def write_table(out: str, rows: list[dict], checkpoints: list[str]) -> None:
    """``rows`` as a CSV at ``out``, the models' hashes beside it, and the table printed."""
    table = pd.DataFrame(rows)
    table.to_csv(out, index=False)
    write_provenance_beside(out, provenance({Path(c).name: c for c in checkpoints}, seeds=[SEED]))
    print(table.to_string(index=False))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
