"""A CMVAE that averages each frame's reading with its mirror image's: exactly symmetric, in torch and ONNX alike,
carried by its checkpoint, trained and resumed as such. Real torch, real checkpoints, the shipped light model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.export import export_checkpoint
from encoder_service.inference import LatentEncoder
from encoder_service.model import (
    CMVAE,
    PSI,
    CircularPsiReader,
    images_to_tensor,
    load_model,
    make_checkpoint,
    mirror_signs,
    with_prior,
)
from encoder_service.train import run
from services.geometry import LABEL_NAMES, VERTICAL_LABEL_NAMES
from swimm.cli import main as swimm
from tests.encoder.cmvae_testdata import write_dataset
from tests.encoder.quick_training import quick_settings

MODELS = Path(__file__).parents[2] / "encoder_service" / "models"
LIGHT = MODELS / "cmvae_light.pt"


def _frames(tmp_path: Path) -> np.ndarray:
    dataset = write_dataset(tmp_path / "data", count=8, seed=5, shard_size=8)
    return np.load(dataset / "shard-00000.images.npy")


def test_signs_negate_theta_and_psi_and_keep_the_rest() -> None:
    assert mirror_signs(LABEL_NAMES, 10) == (1.0, -1.0, -1.0) + (1.0,) * 7
    assert mirror_signs(VERTICAL_LABEL_NAMES, 5) == (1.0, -1.0, -1.0, 1.0, 1.0)


@pytest.mark.parametrize("options", [{"input_norm": "light"}, {"input_norm": "channel", "track": True}])
def test_a_frame_and_its_mirror_image_read_as_mirrors(tmp_path: Path, options: dict) -> None:
    """d and every latent no flip negates read the same on a frame and its mirror image; theta and psi read
    negated. A tracking model's prior stripe flips with its frame."""
    torch.manual_seed(7)
    model = CMVAE(mirror_average=True, **options).eval()
    frames = images_to_tensor(_frames(tmp_path))
    if model.tracks:
        frames = with_prior(frames, torch.linspace(-20.0, 30.0, len(frames)))
    with torch.no_grad():
        mu, logvar = model.encode(frames)
        mu_mirror, logvar_mirror = model.encode(frames.flip(-1))
    signs = torch.tensor(mirror_signs(model.labels, model.n_z))
    torch.testing.assert_close(mu_mirror, signs * mu, atol=1e-5, rtol=0)
    torch.testing.assert_close(logvar_mirror, logvar, atol=1e-5, rtol=0)
    assert mu[:, 1].abs().max() > 1e-3  # not symmetric by being zero


def test_the_shipped_light_model_averaged_reads_the_mean_of_its_two_readings(tmp_path: Path) -> None:
    """The average is the plain model's readings of the frame and of its mirror image, the mirror's theta and psi
    negated; `swimm export-encoder --mirror-average` sets the flag in the checkpoint on the plain model's weights,
    and exporting again without the flag keeps it."""
    plain, _ = load_model(LIGHT)
    path = tmp_path / "light_mirror.pt"
    assert swimm(["export-encoder", "--checkpoint", str(LIGHT), "--out", str(path), "--mirror-average"]) == 0
    kept = export_checkpoint(path, tmp_path / "again.pt")
    averaged, saved = load_model(kept)
    assert averaged.mirror_averages and not plain.mirror_averages and saved["config"]["mirror_average"]
    assert not load_model(export_checkpoint(path, tmp_path / "plain.pt", mirror_average=False))[0].mirror_averages
    frames = images_to_tensor(_frames(tmp_path)).float()
    with torch.no_grad():
        mu_frame, _ = plain.float().encode(frames)
        mu_mirror, _ = plain.encode(frames.flip(-1))
        mu, _ = averaged.float().encode(frames)
    expected = (mu_frame + torch.tensor(mirror_signs(plain.labels, plain.n_z)) * mu_mirror) / 2
    torch.testing.assert_close(mu, expected, atol=1e-5, rtol=0)
    assert not torch.allclose(mu, mu_frame, atol=1e-3)


def _wrapped_degrees(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + 180.0, 360.0) - 180.0


def _linear_decoder(scale: float) -> torch.nn.Sequential:
    """A state decoder's shape reading z * scale exactly: relu(z) - relu(-z) carried through both hidden layers."""
    torch.manual_seed(0)
    model = CMVAE(n_z=3)
    layers = model.state_decoders[PSI].mlp
    with torch.no_grad():
        for layer in (layers[0], layers[2], layers[4]):
            layer.weight.zero_(), layer.bias.zero_()
        layers[0].weight[:2, 0] = torch.tensor([1.0, -1.0])
        layers[2].weight[0, 0] = layers[2].weight[1, 1] = 1.0
        layers[4].weight[0, :2] = torch.tensor([scale, -scale])
    return layers


def test_psi_averages_round_the_circle_where_a_plain_average_turns_the_dolphin_round() -> None:
    """With a psi decoder reading 45 deg per latent unit: a frame read at +179 deg whose mirror image reads +179
    (-179 negated) averages to 180 deg, where the plain average of latents gives 0, facing the camera; reads on
    one side of the wrap average as angles do (45 and -(-54) -> 49.5)."""
    reader = CircularPsiReader()
    reader.tabulate(_linear_decoder(1 / 4))  # normalised psi z/4 -> 45 deg per unit
    own, mirror = torch.tensor([179 / 45, 1.0]), torch.tensor([179 / 45, -54 / 45])
    read = _wrapped_degrees(45.0 * reader(own, mirror))
    assert abs(abs(float(read[0])) - 180.0) < 0.2
    assert abs(float(read[1]) - 49.5) < 0.2
    assert abs(float(_wrapped_degrees(45.0 * (own[0] - mirror[0]) / 2))) < 0.2  # the plain average's turn


def test_the_shipped_vertical_model_read_with_psi_round_the_circle(tmp_path: Path) -> None:
    """`swimm export-encoder --circular-psi` on a mirror-averaging model: every latent but psi reads the plain mirror
    average; psi decodes to the circular mean of the frame's own psi and its mirror image's negated. Without a
    mirror average the flag is refused by name, and nothing is written."""
    source = export_checkpoint(MODELS / "cmvae_vertical.pt", tmp_path / "averaged.pt", circular_psi=False)
    path = tmp_path / "circular.pt"
    assert swimm(["export-encoder", "--checkpoint", str(source), "--out", str(path), "--circular-psi"]) == 0
    circular, saved = load_model(path)
    averaged, _ = load_model(source)
    assert saved["config"]["circular_psi"] and circular.circular_psi and not averaged.circular_psi
    plain = load_model(export_checkpoint(source, tmp_path / "plain.pt", mirror_average=False))[0]
    frames = images_to_tensor(_frames(tmp_path)).float()
    with torch.no_grad():
        mu, _ = circular.encode(frames)
        mu_averaged, _ = averaged.encode(frames)
        own, mirror = (
            plain.decode_state(plain.encode(images)[0])[:, PSI] * 180.0 for images in (frames, frames.flip(-1))
        )
        psi = circular.decode_state(mu)[:, PSI] * 180.0
    others = [index for index in range(circular.n_z) if index != PSI]
    torch.testing.assert_close(mu[:, others], mu_averaged[:, others], atol=1e-5, rtol=0)
    own_rad, mirror_rad = torch.deg2rad(own), -torch.deg2rad(mirror)
    mean = torch.rad2deg(torch.atan2(own_rad.sin() + mirror_rad.sin(), own_rad.cos() + mirror_rad.cos()))
    assert float(_wrapped_degrees(psi - mean).abs().max()) < 0.5
    with pytest.raises(ValueError, match="--circular-psi"):
        export_checkpoint(source, tmp_path / "refused.pt", mirror_average=False, circular_psi=True)
    assert not (tmp_path / "refused.pt").exists()


@pytest.mark.parametrize("circular_psi", [False, True])
def test_onnx_reads_a_mirror_averaging_model_as_torch_does(tmp_path: Path, circular_psi: bool) -> None:
    torch.manual_seed(3)
    path = tmp_path / "mirror.pt"
    model = CMVAE(input_norm="light", mirror_average=True, circular_psi=circular_psi)
    torch.save(make_checkpoint(model, beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    frames = _frames(tmp_path)
    torch_mu, _ = LatentEncoder(path, threads=1).encode(frames)
    onnx_mu, _ = LatentEncoder(path, engine="onnx").encode(frames)
    np.testing.assert_allclose(onnx_mu, torch_mu, atol=1e-4)


def test_a_run_trains_a_mirror_averaging_model_and_resumes_only_as_one(tmp_path: Path) -> None:
    dataset = write_dataset(tmp_path / "data", count=64, seed=3, shard_size=32)
    out = tmp_path / "run"
    assert run(quick_settings(dataset, out, mirror_average=True)) == 0
    model, checkpoint = load_model(out / "best.pt")
    assert checkpoint["config"]["mirror_average"] and model.mirror_averages
    with pytest.raises(ValueError, match="mirror_average=True"):
        run(quick_settings(dataset, out, epochs=2, resume=True))
    assert run(quick_settings(dataset, out, epochs=2, resume=True, mirror_average=True)) == 0
    assert torch.load(out / "last.pt", weights_only=True)["epoch"] == 2
