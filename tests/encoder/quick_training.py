"""Settings of the short training runs the encoder tests make on the CPU."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from encoder_service.model import CMVAE, images_to_tensor, load_model
from encoder_service.train import TrainEncoderSettings, load_init_weights

GENERAL = Path(__file__).parents[2] / "encoder_service" / "models" / "cmvae_general.pt"


def quick_settings(dataset: Path, out: Path, **overrides: object) -> TrainEncoderSettings:
    """One epoch on the CPU, a quarter of the rows held out, no TensorBoard or batch-norm re-estimation;
    ``overrides`` set what a test is about."""
    base = {"dataset": [str(dataset)], "out": str(out), "epochs": 1, "val_fraction": 0.25, "device": "cpu",
            "tensorboard": False, "bn_batches": 0}  # fmt: skip
    return TrainEncoderSettings(**{**base, **overrides})


def started_from_general(dataset: Path, **options: bool) -> tuple[CMVAE, CMVAE, torch.Tensor]:
    """A channel-norm CMVAE with ``options`` (locate, track) initialised from `cmvae_general.pt`, that checkpoint
    itself, and eight of ``dataset``'s frames: what a test of an optional part starting as its checkpoint needs."""
    started = CMVAE(input_norm="channel", **options)
    load_init_weights(started, str(GENERAL), n_z=10)
    general, _ = load_model(GENERAL)
    frames = images_to_tensor(np.load(dataset / "shard-00000.images.npy")[:8])
    return started.eval(), general, frames
