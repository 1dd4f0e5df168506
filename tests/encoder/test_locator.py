"""The locator: an encoder that reads where the dolphin is off a map the masks train, at inference too."""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.export import export_checkpoint
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, images_to_tensor, load_model, soft_argmax
from encoder_service.train import run
from tests.encoder.quick_training import quick_settings, started_from_general


@pytest.fixture(scope="module")
def masked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; read when MuJoCo is first imported
    from sim_service.dataset import write_dataset

    root = tmp_path_factory.mktemp("locator") / "masked"
    return write_dataset(root, count=96, seed=4, shard_size=48, progress=False, masks=True)


_settings = partial(quick_settings, locate=True, mask_weight=1.0, input_norm="channel")


def test_soft_argmax_is_the_expected_cell_centre() -> None:
    logits = torch.full((2, 8, 8), -50.0)
    logits[0, 2, 5] = 50.0  # row 2, column 5: centres at -7/8 + 2 * 2/8 and -7/8 + 5 * 2/8
    logits[1, :, 0] = logits[1, :, 7] = 50.0  # the two outer columns, every row: the middle on average
    np.testing.assert_allclose(soft_argmax(logits).numpy(), [[0.375, -0.375], [0.0, 0.0]], atol=1e-6)


def test_a_locating_encoder_starts_as_the_model_it_is_initialised_from(masked: Path) -> None:
    """The head reads the soft-argmax through zero weights at first: the latents are the checkpoint's."""
    started, general, frames = started_from_general(masked, locate=True)
    with torch.no_grad():
        torch.testing.assert_close(started.encode(frames), general.encode(frames), rtol=1e-5, atol=1e-5)


def test_a_trained_locator_reaches_inference_export_and_onnx(masked: Path, tmp_path: Path) -> None:
    run(_settings(masked, tmp_path / "run", epochs=2, lr=1e-3, batch_size=16))
    model, checkpoint = load_model(tmp_path / "run" / "last.pt")
    assert "val_mask_iou" in checkpoint["metrics"] or "mask_iou" in checkpoint["metrics"]
    frames = np.load(masked / "shard-00001.images.npy")[:6]
    torch_mu, _ = LatentEncoder(tmp_path / "run" / "last.pt").encode(frames)
    onnx_mu, _ = LatentEncoder(tmp_path / "run" / "last.pt", engine="onnx").encode(frames)
    np.testing.assert_allclose(onnx_mu, torch_mu, rtol=1e-4, atol=1e-4)

    exported = export_checkpoint(tmp_path / "run" / "last.pt", tmp_path / "exported.pt")
    kept = torch.load(exported, weights_only=True)
    assert kept["config"]["locate"] is True and any(name.startswith("encoder.locator.") for name in kept["state_dict"])
    exported_mu, _ = LatentEncoder(exported).encode(frames)
    np.testing.assert_allclose(exported_mu, torch_mu, atol=2e-2)  # float16 weights

    with torch.no_grad():  # the latent does depend on where the locator looks
        model.encoder.locator.layers[-1].bias += 5.0 * torch.randn(1)
        model.encoder.locator.layers[-1].weight.mul_(-3.0)
        moved = model.encode(images_to_tensor(frames))[0].numpy()
    assert np.abs(moved - torch_mu).max() > 1e-3


def test_refusals_name_what_is_wrong(masked: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--locate .* --mask-weight > 0"):
        run(_settings(masked, tmp_path / "no-masks", mask_weight=0.0))
    with pytest.raises(ValueError, match="no mask head besides"):
        CMVAE(mask_head=True, locate=True)
    run(_settings(masked, tmp_path / "plain", locate=False, mask_weight=0.0))
    with pytest.raises(ValueError, match="locate=False: resume it so"):
        run(_settings(masked, tmp_path / "plain", epochs=2, resume=True))
