"""How each CMVAE reads the dolphin in every condition of the generalisation suite: d and theta errors on the
selection seed's (211) reset frames, a minute a model rather than a suite's episodes (docs/encoder.md, "A low
sun's shafts in perspective"). A distance read biased near in one water shows here before a policy pays for it.

    MUJOCO_GL=egl python docs/encoder/selection/condition_reads.py OUT.csv CHECKPOINT [CHECKPOINT ...]
"""

import sys
from pathlib import Path

from detector_frames import condition_frames
from fan_overlay import errors
from low_sun_ablation import SEED, write_table

from encoder_service.inference import LatentEncoder
from eval_service.suite import SuiteSettings, suite_conditions
from sim_service.settings import WorldSettings
from sim_service.world import World

FRAMES = 100


def main(out: str, checkpoints: list[str]) -> None:
    world = World(WorldSettings())
    frames = {split.name: condition_frames(world, split, SEED, FRAMES) for split in suite_conditions(SuiteSettings())}
    world.close()
    rows = []
    for checkpoint in checkpoints:
        encoder, model = LatentEncoder(checkpoint), Path(checkpoint).name
        rows += [{"checkpoint": model, "condition": name, **errors(encoder, *read)} for name, read in frames.items()]
    write_table(out, rows, checkpoints)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
