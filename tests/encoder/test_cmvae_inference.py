"""LatentEncoder on a saved checkpoint: the same numbers as the model, clear refusals of bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, denormalise_labels, images_to_tensor, make_checkpoint


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> tuple[CMVAE, Path]:
    torch.manual_seed(1)
    model = CMVAE(n_z=10)
    with torch.no_grad():  # non-trivial batch-norm statistics, so eval mode differs from train mode
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
    path = tmp_path_factory.mktemp("cmvae-inference") / "cmvae.pt"
    torch.save(make_checkpoint(model, beta=8.0, epoch=3, val_loss=0.5, metrics={"total": 0.5}), path)
    return model.eval(), path


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    return np.random.default_rng(2).integers(0, 256, size=(5, 64, 64, 3), dtype=np.uint8)


def test_encode_matches_the_eval_mode_model(saved: tuple[CMVAE, Path], frames: np.ndarray) -> None:
    model, path = saved
    encoder = LatentEncoder(path, threads=1)
    assert encoder.n_z == 10 and encoder.trained_epochs == 3
    mu, logvar = encoder.encode(frames)
    assert mu.shape == logvar.shape == (5, 10) and mu.dtype == logvar.dtype == np.float32
    with torch.no_grad():
        expected_mu, expected_logvar = model.encode(images_to_tensor(frames))
    np.testing.assert_allclose(mu, expected_mu.numpy(), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(logvar, expected_logvar.numpy(), rtol=1e-4, atol=1e-5)
    single_mu, _ = encoder.encode(frames[2:3])  # batch size is free; rows do not influence each other
    np.testing.assert_allclose(single_mu[0], mu[2], rtol=1e-4, atol=1e-5)


def test_decode_state_returns_physical_units(saved: tuple[CMVAE, Path], frames: np.ndarray) -> None:
    model, path = saved
    encoder = LatentEncoder(path)
    mu, _ = encoder.encode(frames)
    d, theta, psi = encoder.decode_state(mu)
    assert d.shape == theta.shape == psi.shape == (5,)
    with torch.no_grad():
        expected = denormalise_labels(model.decode_state(torch.from_numpy(mu)).numpy())
    np.testing.assert_allclose(np.stack([d, theta, psi], axis=1), expected, rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match=r"\(N, 10\)"):
        encoder.decode_state(np.zeros((2, 3), dtype=np.float32))
    assert encoder.labels == ("d", "theta", "psi")


def test_a_vertical_model_decodes_the_elevation_too(tmp_path: Path, frames: np.ndarray) -> None:
    torch.manual_seed(3)
    labels = ("d", "theta", "psi", "elevation")
    model = CMVAE(n_z=10, labels=labels).eval()
    torch.save(make_checkpoint(model, beta=8.0, epoch=1, val_loss=0.5, metrics={}), tmp_path / "vertical.pt")
    encoder = LatentEncoder(tmp_path / "vertical.pt")
    mu, _ = encoder.encode(frames)
    decoded = encoder.decode_state(mu)
    assert encoder.labels == labels and len(decoded) == 4
    with torch.no_grad():
        expected = denormalise_labels(model.decode_state(torch.from_numpy(mu)).numpy(), labels)
    np.testing.assert_allclose(np.stack(decoded, axis=1), expected, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize(
    ("images", "message"),
    [
        (np.zeros((2, 64, 64, 3), dtype=np.float32), "uint8, got float32"),
        (np.zeros((64, 64, 3), dtype=np.uint8), r"got \(64, 64, 3\)"),
        (np.zeros((2, 32, 32, 3), dtype=np.uint8), r"got \(2, 32, 32, 3\)"),
        (np.zeros((2, 64, 64, 4), dtype=np.uint8), r"got \(2, 64, 64, 4\)"),
        (np.zeros((0, 64, 64, 3), dtype=np.uint8), "N>0"),
        ([[0]], "numpy array"),
    ],
)
def test_bad_images_are_refused(saved: tuple[CMVAE, Path], images: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        LatentEncoder(saved[1]).encode(images)


def test_missing_checkpoint_names_the_path_and_the_command(tmp_path: Path) -> None:
    missing = tmp_path / "nothing.pt"
    with pytest.raises(FileNotFoundError, match="swimm train-encoder") as caught:
        LatentEncoder(missing)
    assert str(missing) in str(caught.value)


def test_a_foreign_file_is_not_taken_for_a_checkpoint(tmp_path: Path) -> None:
    path = tmp_path / "other.pt"
    torch.save({"format": "something-else"}, path)
    with pytest.raises(ValueError, match="not a swimm-cmvae checkpoint"):
        LatentEncoder(path)


def test_the_onnx_engine_gives_torchs_latents_and_the_same_latent_in_any_batch(
    saved: tuple[CMVAE, Path], frames: np.ndarray
) -> None:
    _, path = saved
    torch_mu, torch_logvar = LatentEncoder(path, threads=1).encode(frames)
    onnx = LatentEncoder(path, engine="onnx")
    mu, logvar = onnx.encode(frames)
    np.testing.assert_allclose(mu, torch_mu, atol=1e-4)
    np.testing.assert_allclose(logvar, torch_logvar, atol=1e-4)
    alone = np.concatenate([onnx.encode(frames[row : row + 1])[0] for row in range(len(frames))])
    np.testing.assert_array_equal(alone, mu)  # batch-invariant: grouped envs see the latents of single ones


@pytest.mark.parametrize(("engine", "device"), [("tensorrt", "cpu"), ("onnx", "cuda")])
def test_an_unknown_engine_or_onnx_off_the_cpu_is_refused(saved: tuple[CMVAE, Path], engine: str, device: str) -> None:
    with pytest.raises(ValueError, match=f"encoder engine must be one of torch, onnx .* got '{engine}' on '{device}'"):
        LatentEncoder(saved[1], device=device, engine=engine)
