"""Which reader to trust, frame by frame: on each suite condition's reset frames, the CMVAE's reading errors beside
its own log-variances, and the pod detector's engaged reading, the score of its peak, and the errors of a reading
that takes the detector's only where that score reaches a gate (docs/encoder.md, "Both readings, where the
detector is sure"). A diagnostic, not a result:

    MUJOCO_GL=egl python docs/encoder/selection/peak_scores.py encoder_service/models/cmvae_wide.pt runs/det-ctl.pt \
        --out docs/encoder/selection/detector/peak-scores.csv
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from detector_frames import condition_frames

from encoder_service.inference import LatentEncoder
from encoder_service.pod_encoder import PodEncoder
from eval_service.suite import SuiteSettings, suite_conditions
from sim_service.settings import WorldSettings
from sim_service.world import World

GATES = (0.5, 0.7, 0.8, 0.9)
FOUND_DEG = 2.5  # an engaged peak this near the dolphin's azimuth is the dolphin


def condition_row(cmvae: LatentEncoder, pod: PodEncoder, frames: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    mu, logvar = cmvae.encode(frames)
    cmvae_d, cmvae_theta, *_ = cmvae.decode_state(mu)
    cmvae_errors = np.abs(np.stack([cmvae_d, cmvae_theta], axis=1) - labels[:, :2])
    engaged = np.full((len(frames), 3), np.nan)  # d error, theta error, peak score
    for row, (detections, truth) in enumerate(zip(pod.detect(frames), labels, strict=True)):
        _, reading = pod.tracker.update(None, detections)
        if reading is not None:
            peak = int(np.argmin(np.abs(detections.azimuth - reading[1])))
            engaged[row] = (abs(reading[0] - truth[0]), abs(reading[1] - truth[1]), detections.score[peak])
    seen = ~np.isnan(engaged[:, 0])
    found = seen & (engaged[:, 1] < FOUND_DEG)
    row = {
        "frames": len(frames),
        "cmvae_d_mae_m": cmvae_errors[:, 0].mean(),
        "cmvae_theta_mae_deg": cmvae_errors[:, 1].mean(),
        "cmvae_logvar_d": logvar[:, 0].mean(),
        "cmvae_logvar_theta": logvar[:, 1].mean(),
        "corr_logvar_error_d": np.corrcoef(logvar[:, 0], cmvae_errors[:, 0])[0, 1],
        "corr_logvar_error_theta": np.corrcoef(logvar[:, 1], cmvae_errors[:, 1])[0, 1],
        "detector_d_mae_m": np.nanmean(engaged[:, 0]),
        "detector_theta_mae_deg": np.nanmean(engaged[:, 1]),
        "engaged_none": np.mean(~seen),
        "engaged_not_dolphin": np.mean(seen & ~found),
        "score_median_dolphin": np.median(engaged[found, 2]) if found.any() else np.nan,
        "score_median_not_dolphin": np.median(engaged[seen & ~found, 2]) if (seen & ~found).any() else np.nan,
    }
    for gate in GATES:
        use = seen & (np.nan_to_num(engaged[:, 2]) >= gate)
        row[f"gate_{gate}_detector_share"] = use.mean()
        row[f"gate_{gate}_d_mae_m"] = np.where(use, engaged[:, 0], cmvae_errors[:, 0]).mean()
        row[f"gate_{gate}_theta_mae_deg"] = np.where(use, engaged[:, 1], cmvae_errors[:, 1]).mean()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cmvae")
    parser.add_argument("detector")
    parser.add_argument("--seed", type=int, default=211)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    cmvae, pod = LatentEncoder(args.cmvae), PodEncoder(args.detector)
    world = World(WorldSettings())
    rows = []
    for split in suite_conditions(SuiteSettings()):
        frames, labels = condition_frames(world, split, args.seed, args.frames)
        rows.append({"condition": split.name} | condition_row(cmvae, pod, frames, labels))
        print({name: round(value, 3) if isinstance(value, float) else value for name, value in rows[-1].items()},
              flush=True)  # fmt: skip
    world.close()
    pd.DataFrame(rows).to_csv(args.out, index=False, float_format="%.3f")


if __name__ == "__main__":
    main()
