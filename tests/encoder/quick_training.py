"""Settings of the short training runs the encoder tests make on the CPU."""

from __future__ import annotations

from pathlib import Path

from encoder_service.train import TrainEncoderSettings


def quick_settings(dataset: Path, out: Path, **overrides: object) -> TrainEncoderSettings:
    """One epoch on the CPU, a quarter of the rows held out, no TensorBoard or batch-norm re-estimation;
    ``overrides`` set what a test is about."""
    base = {"dataset": [str(dataset)], "out": str(out), "epochs": 1, "val_fraction": 0.25, "device": "cpu",
            "tensorboard": False, "bn_batches": 0}  # fmt: skip
    return TrainEncoderSettings(**{**base, **overrides})
