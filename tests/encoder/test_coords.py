"""A CoordConv encoder (`swimm train-encoder --coords`): the pixels' column and row as two more input channels."""

from pathlib import Path

import numpy as np
import torch

from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, COORDINATE_CHANNELS, coordinate_planes, images_to_tensor, make_checkpoint
from encoder_service.train import load_init_weights


def test_the_coordinate_planes_run_left_to_right_and_top_to_bottom() -> None:
    planes = coordinate_planes(torch.zeros(2, 3, 64, 64))
    assert planes.shape == (2, 2, 64, 64)
    column, row = planes[1]
    assert column[0, 0] == -1.0 and column[0, -1] == 1.0 and torch.all(column[:, 5] == column[0, 5])
    assert row[0, 0] == -1.0 and row[-1, 0] == 1.0 and torch.all(row[5, :] == row[5, 0])


def test_a_coords_model_reads_them_after_every_other_channel() -> None:
    model = CMVAE(input_norm="light", track=True, coords=True)
    assert model.encoder.input_channels[-2:] == COORDINATE_CHANNELS
    assert model.encoder.features[0].in_channels == len(model.encoder.input_channels) == 9


def test_a_coords_model_started_from_one_without_reads_as_it(tmp_path: Path) -> None:
    """The coordinates come in through zero weights, so a fine-tune starts exactly where its checkpoint was."""
    torch.manual_seed(11)
    path = tmp_path / "plain.pt"
    original = CMVAE(input_norm="light", mirror_average=True).eval()
    torch.save(make_checkpoint(original, beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    model = CMVAE(input_norm="light", mirror_average=True, coords=True).eval()
    load_init_weights(model, str(path), n_z=10)
    frames = images_to_tensor(np.random.default_rng(12).integers(0, 256, (4, 64, 64, 3), dtype=np.uint8))
    with torch.no_grad():
        torch.testing.assert_close(model.encode(frames), original.encode(frames), rtol=1e-5, atol=1e-5)
        model.encoder.features[0].weight[:, -2:] = 0.1  # once trained, where a feature lies changes the reading
        assert not torch.allclose(model.encode(frames)[0], original.encode(frames)[0], atol=1e-3)


def test_a_coords_model_travels_in_its_checkpoint_and_runs_the_same_in_onnx(tmp_path: Path) -> None:
    torch.manual_seed(13)
    model = CMVAE(coords=True, mirror_average=True)
    with torch.no_grad():
        model.encoder.features[0].weight[:, -2:].normal_()
    path = tmp_path / "coords.pt"
    torch.save(make_checkpoint(model, beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    frames = np.random.default_rng(14).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    torch_mu, _ = LatentEncoder(path, threads=1).encode(frames)
    onnx_mu, _ = LatentEncoder(path, engine="onnx").encode(frames)
    np.testing.assert_allclose(onnx_mu, torch_mu, atol=1e-4)
    single_mu, _ = LatentEncoder(path, engine="onnx").encode(frames[:1])  # a batch of one reads the same
    np.testing.assert_allclose(single_mu, onnx_mu[:1], atol=1e-5)
