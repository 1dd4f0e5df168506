"""`swimm export-encoder`: turn a training checkpoint into the small file the project ships.

A training checkpoint holds float32 weights (21 MB for the SPEC's CMVAE, most of it the image decoder's
transposed convolutions). The shipped default keeps every weight, so `swimm eval-encoder` can still draw
reconstructions, but in float16: half the size, and loading casts back to float32, so inference code is
unchanged. The rounding moves latents by about 1e-3 of their spread (measured in the tests), far below what
the encoder's own error is; a policy trained on the shipped file sees exactly what it will see in service.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from encoder_service.inference import DEFAULT_CHECKPOINT
from encoder_service.model import read_checkpoint

log = logging.getLogger(__name__)


@dataclass
class ExportEncoderSettings:
    checkpoint: str = "runs/cmvae/best.pt"  # written by `swimm train-encoder`
    out: str = str(DEFAULT_CHECKPOINT)
    # read each frame averaged with its mirror image (encoder_service.model.mirror_signs); unset keeps the source's
    mirror_average: bool | None = None
    overwrite: bool = False  # replace an existing --out (the default --out is the shipped model)


def export_checkpoint(source: str | Path, destination: str | Path, mirror_average: bool | None = None) -> Path:
    """Write ``source``'s weights as float16, with its config and metrics, and nothing needed only to resume or train
    (a mask head is dropped). ``mirror_average`` sets how the exported model reads a frame (None keeps the source's):
    the flag adds no weight, so any model can be shipped mirror-averaged."""
    checkpoint = read_checkpoint(source)
    kept = {key: checkpoint[key] for key in ("format", "version", "config", "epoch", "val_loss", "metrics")}
    kept["config"] = {**checkpoint["config"], "mask_head": False}  # a training aid: nothing downstream reads it
    if mirror_average is not None:
        kept["config"]["mirror_average"] = mirror_average
    kept["state_dict"] = {
        name: tensor.half() if tensor.is_floating_point() else tensor
        for name, tensor in checkpoint["state_dict"].items()
        if not name.startswith("mask_head.")
    }
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    torch.save(kept, destination)
    reading = "mirror-averaged" if kept["config"].get("mirror_average") else "plain"
    log.info("wrote %s (%.1f MB, %s reading) from %s", destination, destination.stat().st_size / 1e6, reading, source)
    return destination


def check(settings: ExportEncoderSettings) -> None:
    """Refuse a source that is no CMVAE checkpoint, and an --out that would replace a model, before writing."""
    read_checkpoint(settings.checkpoint)
    if Path(settings.out).exists() and not settings.overwrite:
        raise FileExistsError(f"--out {settings.out} exists: give --overwrite to replace it, or choose another --out")


def run(settings: ExportEncoderSettings) -> None:
    check(settings)
    export_checkpoint(settings.checkpoint, settings.out, settings.mirror_average)
