"""The shipped-model export: half the bytes, the same latents to within float16 rounding."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from encoder_service.export import export_checkpoint
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint, read_checkpoint
from tests.encoder.cmvae_testdata import draw_frames


def test_export_halves_the_file_and_keeps_latents_and_metrics(tmp_path):
    torch.manual_seed(0)
    source = tmp_path / "best.pt"
    torch.save(make_checkpoint(CMVAE(), beta=8.0, epoch=3, val_loss=0.1, metrics={"mae_d": 0.3}), source)
    shipped = export_checkpoint(source, tmp_path / "models" / "cmvae.pt")

    assert shipped.stat().st_size < 0.55 * source.stat().st_size
    assert read_checkpoint(shipped)["metrics"] == {"mae_d": 0.3}
    frames = draw_frames(np.array([[3.0, 10.0, 0.0], [6.0, -20.0, 90.0], [9.0, 0.0, 180.0]], dtype=np.float32))
    mu_full, _ = LatentEncoder(source).encode(frames)
    mu_half, _ = LatentEncoder(shipped).encode(frames)
    spread = np.abs(mu_full).max()
    assert np.abs(mu_half - mu_full).max() < 1e-2 * spread


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"not a checkpoint", "is not a swimm-cmvae checkpoint: torch cannot read it \\(UnpicklingError\\)"),
        (b"render_scale: 2\n", "is not a swimm-cmvae checkpoint: torch cannot read it"),
        (None, "is not a swimm-cmvae checkpoint$"),  # a torch file holding something else
    ],
)
def test_a_file_that_is_no_cmvae_checkpoint_is_refused_by_name(tmp_path, content, reason):
    path = tmp_path / "model.pt"
    if content is None:
        torch.save({"weights": torch.zeros(2)}, path)
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError, match=f"{re.escape(str(path))} {reason}"):
        read_checkpoint(path)
    with pytest.raises(FileNotFoundError, match="does not exist \\(make one with `swimm train-encoder`\\)"):
        read_checkpoint(tmp_path / "missing.pt")
