"""`swimm export-encoder`: turn a training checkpoint into the small file the project ships.

A training checkpoint holds float32 weights (21 MB for the SPEC's CMVAE, most of it the image decoder's
transposed convolutions). The shipped default keeps every weight, so `swimm eval-encoder` can still draw
reconstructions, but in float16: half the size, and loading casts back to float32, so inference code is
unchanged. The rounding moves latents by about 1e-3 of their spread (measured in the tests), far below what
the encoder's own error is; a policy trained on the shipped file sees exactly what it will see in service.

`--average` exports the mean of several checkpoints of one model, weight by weight: a fine-tune's epochs (kept by
`swimm train-encoder --keep-epochs`) read the dolphin with offsets that swing from epoch to epoch, and their mean
lies between them (stochastic weight averaging).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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
    # take psi's mirror average round the circle (encoder_service.model.CircularPsiReader); unset keeps the source's
    circular_psi: bool | None = None
    overwrite: bool = False  # replace an existing --out (the default --out is the shipped model)
    # more checkpoints of the same model (one run's epochs) averaged with --checkpoint, weight by weight
    average: list[str] = field(default_factory=list)


def averaged(checkpoints: dict[str, dict[str, Any]]) -> dict[str, torch.Tensor]:
    """The weight-by-weight mean of checkpoints of one architecture (batch-norm statistics included; counters are
    the first's); a checkpoint of another model is refused by name."""
    (first_path, first), *others = checkpoints.items()
    for path, checkpoint in others:
        for key in ("n_z", "input_norm", "labels", "locate", "track", "prior_distance"):
            if checkpoint["config"].get(key) != first["config"].get(key):
                raise ValueError(
                    f"--average: {path} has {key}={checkpoint['config'].get(key)!r}, {first_path} "
                    f"{first['config'].get(key)!r}: only checkpoints of one model average"
                )
        if checkpoint["state_dict"].keys() != first["state_dict"].keys():
            raise ValueError(f"--average: {path} holds other weights than {first_path}")
    weights = {}
    for name, tensor in first["state_dict"].items():
        if tensor.is_floating_point():
            stacked = torch.stack([checkpoint["state_dict"][name].float() for checkpoint in checkpoints.values()])
            weights[name] = stacked.mean(dim=0)
        else:
            weights[name] = tensor
    return weights


def export_checkpoint(
    source: str | Path,
    destination: str | Path,
    mirror_average: bool | None = None,
    average: Sequence[str | Path] = (),
    circular_psi: bool | None = None,
) -> Path:
    """Write ``source``'s weights as float16, with its config and metrics, and nothing needed only to resume or train
    (a mask head is dropped). ``mirror_average`` and ``circular_psi`` set how the exported model reads a frame (None
    keeps the source's): the flags add no weight, so any model can be shipped mirror-averaged. ``average`` names
    more checkpoints whose weights are averaged with ``source``'s; the file records their names, and its validation
    loss and metrics stay ``source``'s (nothing validates the mean here: read it with `swimm eval-encoder`)."""
    checkpoint = read_checkpoint(source)
    kept = {key: checkpoint[key] for key in ("format", "version", "config", "epoch", "val_loss", "metrics")}
    if average:
        paths = [str(source), *map(str, average)]
        if len({Path(path).resolve() for path in paths}) < len(paths):
            raise ValueError(f"--checkpoint and --average name one file twice: {paths}")
        sources = {str(source): checkpoint} | {path: read_checkpoint(path) for path in paths[1:]}
        checkpoint = {**checkpoint, "state_dict": averaged(sources)}
        kept["averaged_from"] = paths
        kept["epoch"] = max(source["epoch"] for source in sources.values())  # the training the mean has seen
    kept["config"] = {**checkpoint["config"], "mask_head": False}  # a training aid: nothing downstream reads it
    for key, value in (("mirror_average", mirror_average), ("circular_psi", circular_psi)):
        if value is not None:
            kept["config"][key] = value
    if kept["config"].get("circular_psi") and not kept["config"].get("mirror_average"):
        raise ValueError(f"--circular-psi averages psi's mirror reads round the circle: {source} exported without "
                         "--mirror-average has none")  # fmt: skip
    kept["state_dict"] = {
        name: tensor.half() if tensor.is_floating_point() else tensor
        for name, tensor in checkpoint["state_dict"].items()
        if not name.startswith("mask_head.")
    }
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    torch.save(kept, destination)
    reading = "mirror-averaged" if kept["config"].get("mirror_average") else "plain"
    reading += ", psi round the circle" if kept["config"].get("circular_psi") else ""
    origin = f"the mean of {', '.join(kept['averaged_from'])}" if average else str(source)
    log.info("wrote %s (%.1f MB, %s reading) from %s", destination, destination.stat().st_size / 1e6, reading, origin)
    return destination


def check(settings: ExportEncoderSettings) -> None:
    """Refuse a source that is no CMVAE checkpoint, and an --out that would replace a model, before writing."""
    for path in (settings.checkpoint, *settings.average):
        read_checkpoint(path)
    if Path(settings.out).exists() and not settings.overwrite:
        raise FileExistsError(f"--out {settings.out} exists: give --overwrite to replace it, or choose another --out")


def run(settings: ExportEncoderSettings) -> None:
    check(settings)
    export_checkpoint(
        settings.checkpoint, settings.out, settings.mirror_average, settings.average, settings.circular_psi
    )
