"""Does a locating tracking CMVAE's locator tell a target hidden behind a companion from one in view?

Every frame of a pod dataset with masks (the target's pixels only, so an empty mask is a target hidden behind a
companion) is read with the target's true azimuth as its prior, the prior of a loop that has kept its target.
Prints, for hidden and for visible targets, the quantiles of the locator's peak logit and of its summed cell
probabilities, and how well each separates the two (ROC AUC: 0.5 is no better than chance); writes every frame's
values to a CSV (docs/encoder.md, pods). If the locator told them apart, the loop could keep its last prior while
the target is hidden.

    MUJOCO_GL=egl python docs/encoder/selection/hidden_target.py OUT.csv --dataset data/pod4-test \
        --checkpoint runs/track/e/best.pt
"""

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from encoder_service.data import CMVAEDataset
from encoder_service.model import images_to_tensor, load_model, with_prior
from services.results import provenance, write_provenance_beside

CHUNK = 250
SCORES = ("peak_logit", "summed_probability")


def locator_scores(dataset: CMVAEDataset, checkpoint: str) -> pd.DataFrame:
    model, _ = load_model(checkpoint, "cpu")
    if not (model.tracks and model.locates):
        raise SystemExit(f"{checkpoint} is not a locating tracking CMVAE (swimm train-encoder --track --locate)")
    parts = []
    for start in range(0, len(dataset), CHUNK):
        batch = dataset.read(np.arange(start, min(start + CHUNK, len(dataset))))
        priors = torch.from_numpy(batch.labels[:, 1])
        with torch.inference_mode():
            cells = model.encode_with_mask(with_prior(images_to_tensor(batch.images, "cpu"), priors))[2]
        cells = cells.flatten(1)
        parts.append(pd.DataFrame({
            "row": batch.indices, "d_m": batch.labels[:, 0], "theta_deg": batch.labels[:, 1],
            "target_pixels": batch.masks.reshape(len(batch.masks), -1).sum(axis=1),
            "peak_logit": cells.amax(dim=1).numpy(), "summed_probability": torch.sigmoid(cells).sum(dim=1).numpy(),
        }))  # fmt: skip
    return pd.concat(parts, ignore_index=True)


def auc(score: pd.Series, positive: pd.Series) -> float:
    """The probability that a positive frame scores above a negative one (ties half), from the ranks."""
    ranks = score.rank()
    positives, negatives = int(positive.sum()), int((~positive).sum())
    return float((ranks[positive].sum() - positives * (positives + 1) / 2) / (positives * negatives))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--checkpoint", required=True)
    args = parser.parse_args()
    dataset = CMVAEDataset(args.dataset)
    if not dataset.has_masks:
        raise SystemExit(f"{args.dataset} holds no masks: write it with `swimm dataset --masks`")
    frames = locator_scores(dataset, args.checkpoint)
    frames.to_csv(args.out, index=False)
    write_provenance_beside(args.out, provenance({"cmvae": args.checkpoint}, dataset=str(args.dataset)))
    visible = frames.target_pixels > 0
    for score in SCORES:
        quantiles = {name: frames[score][chosen].quantile([0.1, 0.5, 0.9]).round(2).tolist()
                     for name, chosen in (("hidden", ~visible), ("visible", visible))}  # fmt: skip
        print(f"{score}: 10/50/90% hidden {quantiles['hidden']}, visible {quantiles['visible']}; "
              f"AUC visible over hidden {auc(frames[score], visible):.3f}")  # fmt: skip
    print(f"{int((~visible).sum())} hidden and {int(visible.sum())} visible targets")


if __name__ == "__main__":
    main()
