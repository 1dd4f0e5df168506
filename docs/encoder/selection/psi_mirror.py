"""How a mirror-averaging CMVAE's psi read loses to the wrap at +-180 deg: each frame's labels read three ways.

A mirror-averaging encoder (docs/encoder.md, "each frame read with its mirror image") averages a frame's latents
with its mirror image's, psi's negated. psi is circular but its latent is not: a dolphin seen from behind that
one read puts at +179 deg and the other at -179 averages to a latent that decodes near 0, a dolphin facing the
camera. This reads every frame of a dataset as the encoder does (the averaged latent, psi round the circle for a
model exported `--circular-psi`), from the frame alone, and with psi as the circular mean of the frame's and its
negated mirror's decoded psi (the other labels as averaged), and prints each way's MAE (docs/encoder.md, "Stage j").

    MUJOCO_GL=egl python docs/encoder/selection/psi_mirror.py CHECKPOINT DATASET [DATASET ...]
"""

import sys

import numpy as np
import torch

from encoder_service.data import CMVAEDataset
from encoder_service.inference import load_model
from encoder_service.model import PSI, denormalise_labels, images_to_tensor, label_errors

BATCH = 500


def read(model, images: np.ndarray, mirror_average: bool) -> np.ndarray:
    """Physical labels (N, labels) of ``images``, mirror-averaged or from each frame alone."""
    signs = model.encoder.mirror_signs
    if not mirror_average:
        model.encoder.mirror_signs = None
    try:
        with torch.no_grad():
            parts = [model.decode_state(model.encoder(images_to_tensor(images[i : i + BATCH]))[0]).numpy()
                     for i in range(0, len(images), BATCH)]  # fmt: skip
    finally:
        model.encoder.mirror_signs = signs
    return denormalise_labels(np.concatenate(parts), model.labels)


def main() -> None:
    checkpoint, datasets = sys.argv[1], sys.argv[2:]
    model, _ = load_model(checkpoint, torch.device("cpu"))
    model.eval()
    for root in datasets:
        dataset = CMVAEDataset(root)
        batch = dataset.read(np.arange(len(dataset)))
        shared = min(len(model.labels), batch.labels.shape[1])  # a planar dataset has no elevation to read
        labels, names = batch.labels[:, :shared], model.labels[:shared]
        averaged, alone = read(model, batch.images, True), read(model, batch.images, False)
        mirrored = read(model, np.ascontiguousarray(batch.images[:, :, ::-1]), False)
        circular = averaged.copy()
        frame, mirror = np.radians(alone[:, PSI]), np.radians(-mirrored[:, PSI])
        circular[:, PSI] = np.degrees(np.arctan2(np.sin(frame) + np.sin(mirror), np.cos(frame) + np.cos(mirror)))
        for way, reads in (("as read", averaged), ("frame alone", alone), ("psi circular", circular)):
            errors = label_errors(reads[:, :shared], labels).mean(axis=0)
            print(f"{checkpoint} {root} {way}: " + ", ".join(
                f"{name} {error:.3f}" for name, error in zip(names, errors, strict=True)))  # fmt: skip


if __name__ == "__main__":
    main()
