"""A detector's distance bias per 2 m of true distance on clean lone-dolphin frames after one image change each:
blur, pixel noise, JPEG, a brighter exposure (docs/encoder.md, "A detector for a lone dolphin"). A diagnostic, not
a result: which change of the image moves the distance read, with the water held fixed.

    swimm dataset --out data/lone-clean --count 3000 --seed 31 --workers 2 --masks --dolphin-pod-size 1
    python docs/encoder/selection/detector_swell.py runs/det-ctl.pt data/lone-clean --out det-ctl-swell.csv
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from encoder_service.model import images_to_tensor
from encoder_service.pod_detector import decode
from encoder_service.pod_detector_train import load_pod_dataset
from encoder_service.pod_encoder import load_detector


def changes(rng: np.random.Generator) -> dict:
    def noisy(image: np.ndarray) -> np.ndarray:
        return np.clip(image + rng.normal(0.0, 20.0, image.shape), 0, 255).astype(np.uint8)

    def jpeg(image: np.ndarray) -> np.ndarray:
        return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 20])[1], cv2.IMREAD_COLOR)

    return {
        "none": lambda image: image,
        "blur 1.5 px": lambda image: cv2.GaussianBlur(image, (0, 0), 1.5),
        "blur 3 px": lambda image: cv2.GaussianBlur(image, (0, 0), 3.0),
        "noise 20": noisy,
        "jpeg 20": jpeg,
        "exposure x1.5 + 40": lambda image: np.clip(image * 1.5 + 40, 0, 255).astype(np.uint8),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("detector")
    parser.add_argument("dataset", help="a lone dolphin's dataset with masks (`swimm dataset --masks`)")
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    model, saved = load_detector(args.detector)
    data = load_pod_dataset(Path(args.dataset))
    rows = np.flatnonzero(data["seen"][:, 0])[: args.frames]
    distances, azimuths = data["distances"][rows, 0], data["azimuths"][rows, 0]
    table = []
    for name, change in changes(np.random.default_rng(0)).items():
        frames = np.stack([change(image) for image in data["images"][rows]])
        with torch.no_grad():
            found = decode(*model(images_to_tensor(frames)), saved["threshold"], 64, saved["stride"])
        row = {"change": name}
        for low in (2, 4, 6, 8):
            errors = [peaks.distance[k] - distance
                      for peaks, distance, azimuth in zip(found, distances, azimuths, strict=True) if len(peaks)
                      for k in [int(np.argmin(np.abs(peaks.azimuth - azimuth)))]
                      if abs(peaks.azimuth[k] - azimuth) < 2.5 and low <= distance < low + 2]  # fmt: skip
            row[f"d_bias_{low}_{low + 2}m"] = float(np.mean(errors)) if errors else np.nan
            row[f"found_{low}_{low + 2}m"] = len(errors)
        print(row, flush=True)
        table.append(row)
    pd.DataFrame(table).to_csv(args.out, index=False, float_format="%.3f")


if __name__ == "__main__":
    main()
