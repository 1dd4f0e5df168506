"""A detector's peaks on a lone dolphin's reset frames, per suite condition: frames with no peak, peaks a frame,
and the errors of the peak nearest the dolphin and of the strongest one (docs/encoder.md, "A detector for a lone
dolphin"). With ``--sampled``, frames at the datasets' poses (2 to 10 m) instead, and the distance read's bias per
2 m of true distance. A diagnostic, not a result; the suite's own encoder check reads through the tracker's
engagement rule:

    MUJOCO_GL=egl python docs/encoder/selection/detector_frames.py runs/det-aug.pt --out det-aug-frames.csv
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import torch

from encoder_service.model import images_to_tensor
from encoder_service.pod_detector import decode
from encoder_service.pod_encoder import load_detector
from eval_service.suite import SuiteSettings, suite_conditions
from learner_service.task import episode_seed
from sim_service.dataset import SamplingRanges, labels_and_pose, sample_pose
from sim_service.settings import WorldSettings
from sim_service.splits import Split
from sim_service.world import World


def condition_frames(
    world: World, split: Split, seed: int, count: int, sampled: bool = False
) -> tuple[np.ndarray, ...]:
    """``count`` frames of one suite condition and their (d, theta, psi) labels: the reset frames of ``seed``'s
    episodes 1 to ``count``, or with ``sampled`` the condition's water and scenery at a dataset's poses."""
    frames, labels = [], []
    for index in range(1, count + 1):
        noise = split.noise if split.noise.enabled else False
        telemetry, frame = world.reset(episode_seed(seed, index), noise=noise, scene=split.scene)
        if sampled:  # the split's water and scenery, set by the reset, at a dataset's pose
            telemetry, frame = sample_pose(world, np.random.default_rng([seed, index]), SamplingRanges())
        frames.append(frame)
        labels.append(labels_and_pose(telemetry)[0])
    return np.stack(frames), np.array(labels)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("detector")
    parser.add_argument("--seed", type=int, default=211)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--out", required=True)
    parser.add_argument("--sampled", action="store_true", help="frames at the datasets' poses, not reset frames")
    args = parser.parse_args()
    model, saved = load_detector(args.detector)
    world = World(WorldSettings())
    rows = []
    for split in suite_conditions(SuiteSettings()):
        frames, labels = condition_frames(world, split, args.seed, args.frames, args.sampled)
        with torch.no_grad():
            found = decode(*model(images_to_tensor(frames)), saved["threshold"], 64, saved["stride"])
        nearest, strongest = [], []
        for peaks, (distance, azimuth, _) in zip(found, labels, strict=True):
            if len(peaks):
                k = int(np.argmin(np.abs(peaks.azimuth - azimuth)))
                nearest.append((abs(peaks.azimuth[k] - azimuth), peaks.distance[k] - distance, distance))
                strongest.append(abs(peaks.azimuth[0] - azimuth))
        near = np.array(nearest)
        found_near = near[near[:, 0] < 2.5]  # the dolphin found, not a stray peak beside it
        bins = {
            f"d_bias_{lo}_{lo + 2}m": found_near[(found_near[:, 2] >= lo) & (found_near[:, 2] < lo + 2), 1]
            for lo in (2, 4, 6, 8)
        }
        rows.append({"condition": split.name, "frames": len(frames), "no_peak": sum(len(p) == 0 for p in found),
                     "peaks_per_frame": np.mean([len(p) for p in found]), "nearest_theta_mae_deg": near[:, 0].mean(),
                     "nearest_theta_median_deg": np.median(near[:, 0]), "nearest_d_mae_m": np.abs(near[:, 1]).mean(),
                     "nearest_d_bias_m": near[:, 1].mean(), "strongest_theta_mae_deg": np.mean(strongest),
                     "strongest_within_2_5_deg": np.mean(np.array(strongest) < 2.5)}
                    | {name: errors.mean() if len(errors) else np.nan for name, errors in bins.items()})  # fmt: skip
        print(rows[-1], flush=True)
    world.close()
    pd.DataFrame(rows).to_csv(args.out, index=False, float_format="%.3f")


if __name__ == "__main__":
    main()
