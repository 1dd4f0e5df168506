"""The shipped-model export: half the bytes, the same latents to within float16 rounding."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from encoder_service.export import export_checkpoint
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint, read_checkpoint
from swimm.cli import main as swimm
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


def _random_checkpoint(path, seed: int, **model_options) -> dict:
    torch.manual_seed(seed)
    checkpoint = make_checkpoint(CMVAE(**model_options), beta=8.0, epoch=seed, val_loss=0.1, metrics={})
    torch.save(checkpoint, path)
    return checkpoint


def test_average_exports_the_weight_by_weight_mean_and_names_its_sources(tmp_path):
    sources = [tmp_path / f"epoch-{seed}.pt" for seed in (1, 2, 3)]
    checkpoints = [_random_checkpoint(path, seed) for seed, path in enumerate(sources, start=1)]
    out = tmp_path / "mean.pt"
    assert swimm(["export-encoder", "--checkpoint", str(sources[0]), "--average", str(sources[1]), str(sources[2]),
                  "--out", str(out)]) == 0  # fmt: skip
    exported = read_checkpoint(out)
    assert exported["averaged_from"] == [str(path) for path in sources] and exported["epoch"] == 3
    for name, tensor in exported["state_dict"].items():
        weights = [checkpoint["state_dict"][name] for checkpoint in checkpoints]
        if tensor.is_floating_point():  # float16 keeps about three significant digits
            mean = torch.stack(weights).float().mean(dim=0)
            torch.testing.assert_close(tensor.float(), mean, rtol=1e-3, atol=1e-4)
        else:
            assert torch.equal(tensor, weights[0])
    LatentEncoder(out).encode(draw_frames(np.array([[5.0, 0.0, 0.0]], dtype=np.float32)))


def test_average_refuses_another_model_and_a_file_named_twice_and_writes_nothing(tmp_path):
    first, other = tmp_path / "a.pt", tmp_path / "b.pt"
    _random_checkpoint(first, 1)
    _random_checkpoint(other, 2, n_z=8)
    out = tmp_path / "mean.pt"
    with pytest.raises(ValueError, match=f"--average: {re.escape(str(other))} has n_z=8, {re.escape(str(first))} 10"):
        export_checkpoint(first, out, average=[other])
    with pytest.raises(ValueError, match="--checkpoint and --average name one file twice"):
        export_checkpoint(first, out, average=[tmp_path / "." / "a.pt"])
    assert swimm(["export-encoder", "--checkpoint", str(first), "--average", str(tmp_path / "missing.pt"),
                  "--out", str(out)]) == 2  # fmt: skip
    assert not out.exists()
