"""One dolphin pose at 5, 7 and 9 m rendered in the clean water and three held-out conditions, and a detector's
distance read of each (docs/encoder.md, "A detector for a lone dolphin"): what the unseen waters do to a far
dolphin, to look at.

    MUJOCO_GL=egl python docs/encoder/selection/far_dolphin_look.py runs/det-ctl.pt --out far_dolphin_look.png
"""

from __future__ import annotations

import argparse
import math

import cv2
import numpy as np
import torch

from encoder_service.model import images_to_tensor
from encoder_service.pod_detector import decode
from encoder_service.pod_encoder import load_detector
from eval_service.suite import SuiteSettings, suite_conditions
from learner_service.task import episode_seed
from sim_service.settings import WorldSettings
from sim_service.world import World

CONDITIONS = ("clean", "bright", "sensor", "optics")
DISTANCES_M = (5.0, 7.0, 9.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("detector")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    model, saved = load_detector(args.detector)
    world = World(WorldSettings())
    splits = {split.name: split for split in suite_conditions(SuiteSettings())}
    rows = []
    for name in CONDITIONS:
        split, frames = splits[name], []
        for distance in DISTANCES_M:
            world.reset(episode_seed(211, 1), noise=split.noise if split.noise.enabled else False, scene=split.scene)
            rover = np.array([0.0, 0.0, -4.0])  # the dolphin side-on, a little left of the axis
            _, frame = world.place(
                rover, 0.0, rover + [distance, 0.3, 0.0], math.pi / 2, noise_rng=np.random.default_rng(1)
            )
            frames.append(frame)
        with torch.no_grad():
            found = decode(*model(images_to_tensor(np.stack(frames))), saved["threshold"], 64, saved["stride"])
        reads = [f"{peaks.distance[0]:.2f} m" if len(peaks) else "none" for peaks in found]
        print(f"{name}: true {', '.join(f'{d:.0f} m' for d in DISTANCES_M)}; read {', '.join(reads)}", flush=True)
        rows.append(np.concatenate(frames, axis=1))
    world.close()
    sheet = np.concatenate(rows, axis=0)[..., ::-1]
    cv2.imwrite(args.out, cv2.resize(sheet, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST))


if __name__ == "__main__":
    main()
