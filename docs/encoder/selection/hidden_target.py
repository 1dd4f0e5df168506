"""Whether a locating tracking CMVAE says when its target is hidden: its next prior held where the target shows
no pixel, handed on where it shows.

Every frame of a pod dataset with masks (the target's pixels only, so an empty mask is a target hidden behind a
companion) is read with the target's true azimuth as its prior, the prior of a loop that has kept its target.
Prints, for hidden and for visible targets, the share of frames whose next prior the encoder held, and the theta
error where it handed one on; writes every frame's reading to a CSV (docs/encoder.md, pods).

    MUJOCO_GL=egl python docs/encoder/selection/hidden_target.py OUT.csv --dataset data/pod4-test \
        --checkpoint runs/track/e/best.pt
"""

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from encoder_service.data import CMVAEDataset
from encoder_service.inference import LatentEncoder

CHUNK = 256


def readings(dataset: CMVAEDataset, encoder: LatentEncoder, count: int) -> pd.DataFrame:
    rows = []
    for start in range(0, count, CHUNK):
        batch = dataset.read(np.arange(start, min(start + CHUNK, count)))
        priors = batch.labels[:, 1].astype(np.float32)
        _, _, next_priors = encoder.track(batch.images, priors)
        for index, label, mask, prior, following in zip(batch.indices, batch.labels, batch.masks, priors,
                                                        next_priors, strict=True):  # fmt: skip
            rows.append({"row": int(index), "d_m": float(label[0]), "theta_deg": float(prior),
                         "target_pixels": int(mask.sum()), "held": bool(following == prior),
                         "next_prior_deg": float(following)})  # fmt: skip
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--count", type=int, default=0, help="the first rows only (0: all)")
    args = parser.parse_args()
    dataset = CMVAEDataset(args.dataset)
    if not dataset.has_masks:
        raise SystemExit(f"{args.dataset} holds no masks: write it with `swimm dataset --masks`")
    encoder = LatentEncoder(args.checkpoint)
    frames = readings(dataset, encoder, min(args.count or len(dataset), len(dataset)))
    frames.to_csv(args.out, index=False)
    hidden = frames.target_pixels == 0
    for name, chosen in (("hidden", hidden), ("visible", ~hidden)):
        part = frames[chosen]
        handed = part[~part.held]
        error = (handed.next_prior_deg - handed.theta_deg).abs()
        print(f"{name}: {len(part)} frames, next prior held in {part.held.mean():.3f}; where handed on, theta MAE "
              f"{error.mean():.2f} deg, median {error.median():.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
