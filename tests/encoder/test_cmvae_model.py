"""The CMVAE's modules, loss and label/pixel conversions, on random inputs (CPU, no data on disk)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from encoder_service.model import (
    CMVAE,
    LABEL_NAMES,
    VERTICAL_LABEL_NAMES,
    CMVAEOutput,
    StateLoss,
    cmvae_loss,
    denormalise_labels,
    images_to_tensor,
    label_errors,
    label_ranges,
    normalise_labels,
    state_errors,
    tensor_to_images,
)
from services.geometry import ALPHA_DEG, BETA_DEG


@pytest.fixture(scope="module")
def model() -> CMVAE:
    torch.manual_seed(0)
    return CMVAE(n_z=10).to(memory_format=torch.channels_last)


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(4, 64, 64, 3), dtype=np.uint8)


def test_every_module_output_has_the_spec_shape(model: CMVAE, frames: np.ndarray) -> None:
    images = images_to_tensor(frames)
    model.train()
    with torch.no_grad():
        _check_shapes(model, images)


def _check_shapes(model: CMVAE, images: torch.Tensor) -> None:
    features = model.encoder.features(images)
    assert features.shape == (4, 128 * 2 * 2)  # 64 -> conv 32 -> pool 16 -> blocks 8, 4, 2
    mu, logvar = model.encode(images)
    assert mu.shape == logvar.shape == (4, 10)
    decoded = model.decode_image(mu)
    assert decoded.shape == (4, 3, 64, 64)
    assert float(decoded.min()) >= -1.0 and float(decoded.max()) <= 1.0  # tanh output
    assert model.decode_state(mu).shape == (4, 3)
    for decoder in model.state_decoders:
        assert decoder(mu[:, :1]).shape == (4, 1)
    outputs = model(images)
    assert outputs.z.shape == (4, 10) and outputs.image.shape == (4, 3, 64, 64) and outputs.state.shape == (4, 3)


def test_training_samples_z_and_eval_uses_the_mean(model: CMVAE, frames: np.ndarray) -> None:
    images = images_to_tensor(frames)
    model.eval()
    with torch.no_grad():
        outputs = model(images)
        sampled = model(images, sample=True)
    assert torch.equal(outputs.z, outputs.mu)
    assert float((sampled.z - sampled.mu).abs().max()) > 1e-3


def test_each_state_decoder_reads_only_its_own_latent(model: CMVAE) -> None:
    model.eval()
    z = torch.zeros(1, 10)
    base = model.decode_state(z)
    for dim, changes in [
        (0, (True, False, False)),
        (1, (False, True, False)),
        (2, (False, False, True)),
        (5, (False, False, False)),
    ]:
        moved = z.clone()
        moved[0, dim] = 2.0
        delta = (model.decode_state(moved) - base).abs()[0]
        assert [bool(value > 0) for value in delta] == list(changes)


def test_loss_parts_are_finite_and_kl_scales_with_beta(model: CMVAE, frames: np.ndarray) -> None:
    images = images_to_tensor(frames)
    labels = torch.from_numpy(normalise_labels(np.array([[6.0, 0.0, 0.0]] * 4)))
    model.eval()
    with torch.no_grad():
        outputs = model(images)
    plain = cmvae_loss(outputs, images, labels, beta=0.0)
    heavy = cmvae_loss(outputs, images, labels, beta=8.0)
    for value in plain.as_floats().values():
        assert np.isfinite(value)
    assert plain.kl.item() > 0
    assert plain.total.item() == pytest.approx(plain.image.item() + plain.state.item(), rel=1e-6)
    values_per_image = 64 * 64 * 3  # the KL is weighed per image value, like the per-pixel mean MSE
    # compared as totals, not as their small difference, which float32 rounding dominates
    assert heavy.total.item() == pytest.approx(plain.total.item() + 8.0 * plain.kl.item() / values_per_image, rel=1e-6)


def test_kl_is_zero_at_the_prior_and_matches_the_closed_form() -> None:
    zeros = torch.zeros(2, 10)
    outputs = CMVAEOutput(mu=zeros, logvar=zeros, z=zeros, image=torch.zeros(2, 3, 64, 64), state=torch.zeros(2, 3))
    assert cmvae_loss(outputs, outputs.image, outputs.state, 8.0).kl.item() == pytest.approx(0.0, abs=1e-7)
    outputs.mu = torch.ones(2, 10)  # KL(N(1, 1) || N(0, 1)) = 0.5 per dimension, summed over 10
    parts = cmvae_loss(outputs, outputs.image, outputs.state, 8.0)
    assert parts.kl.item() == pytest.approx(5.0)
    assert parts.total.item() == pytest.approx(8.0 * 5.0 / (3 * 64 * 64))  # beta * KL per image value


def test_label_normalisation_maps_the_ranges_to_minus_one_one_and_back() -> None:
    edges = np.array([[2.0, -ALPHA_DEG, -180.0], [10.0, ALPHA_DEG, 180.0], [6.0, 0.0, 0.0]])
    normalised = normalise_labels(edges)
    np.testing.assert_allclose(normalised, [[-1, -1, -1], [1, 1, 1], [0, 0, 0]], atol=1e-6)
    for names in (LABEL_NAMES, VERTICAL_LABEL_NAMES):
        low, high = label_ranges(names).T
        labels = np.random.default_rng(1).uniform(low, high, size=(100, len(names)))
        np.testing.assert_allclose(denormalise_labels(normalise_labels(labels, names), names), labels, atol=1e-4)


def test_the_elevation_label_spans_the_vertical_field_of_view() -> None:
    vertical = normalise_labels(np.array([[6.0, 0.0, 0.0, -BETA_DEG], [6.0, 0.0, 0.0, BETA_DEG]]), VERTICAL_LABEL_NAMES)
    np.testing.assert_allclose(vertical[:, 3], [-1.0, 1.0], atol=1e-6)
    with pytest.raises(ValueError, match=r"labels \['d', 'theta', 'elevation'\]"):
        CMVAE(labels=("d", "theta", "elevation"))


def test_psi_error_wraps_around_the_circle() -> None:
    errors = label_errors(
        np.array([[3.0, 10.0, 179.0], [5.0, -5.0, -90.0]]), np.array([[2.5, 12.0, -179.0], [5.0, 5.0, 90.0]])
    )
    np.testing.assert_allclose(errors, [[0.5, 2.0, 2.0], [0.0, 10.0, 180.0]], atol=1e-9)


def test_state_loss_takes_psi_the_short_way_round() -> None:
    """psi = 179 deg predicted as -179 costs as little as 2 deg does; d and theta errors are not wrapped."""
    true = torch.from_numpy(normalise_labels(np.array([[2.0, 0.0, 179.0], [6.0, 30.0, -90.0]])))
    predicted = torch.from_numpy(normalise_labels(np.array([[10.0, 0.0, -179.0], [6.0, -30.0, 90.0]])))
    errors = state_errors(predicted, true)
    np.testing.assert_allclose(errors[:, 2].abs().numpy() * 180.0, [2.0, 180.0], atol=1e-3)
    np.testing.assert_allclose(errors[:, :2].numpy(), (predicted - true)[:, :2].numpy())
    assert errors[0, 0].item() == pytest.approx(2.0)  # d from 2 to 10 m spans the whole normalised range


def _state_loss_at(psi_deg: float, labels: torch.Tensor, psi_loss: str) -> float:
    """The state term when every frame's psi is predicted as ``psi_deg`` (d and theta exact)."""
    predicted = labels.clone()
    predicted[:, 2] = psi_deg / 180.0
    zeros = torch.zeros(len(labels), 10)
    outputs = CMVAEOutput(mu=zeros, logvar=zeros, z=zeros, image=torch.zeros(len(labels), 3, 64, 64), state=predicted)
    return cmvae_loss(outputs, outputs.image, labels, 8.0, StateLoss(psi_loss)).state.item()


def test_l1_psi_loss_is_least_at_the_likelier_view_where_mse_is_least_between() -> None:
    """Seven frames of a dolphin facing the camera, three of it facing away, all looking alike.

    The best single answer for MAE is the likelier view (0 deg: 54 deg MAE); the square is least
    near 54 deg, wrong for every frame (75.6 deg MAE).
    """
    labels = torch.from_numpy(normalise_labels(np.array([[6.0, 0.0, 0.0]] * 7 + [[6.0, 0.0, 180.0]] * 3)))
    candidates = np.arange(-180.0, 180.0, 1.0)
    best = {
        loss: candidates[int(np.argmin([_state_loss_at(psi, labels, loss) for psi in candidates]))]
        for loss in ("mse", "l1")
    }
    assert best["l1"] == 0.0
    assert abs(best["mse"]) == pytest.approx(54.0, abs=1.0)
    assert _state_loss_at(30.0, labels, "l1") == pytest.approx((7 * 30 + 3 * 150) / 180 / 10 / 3, rel=1e-5)
    with pytest.raises(ValueError, match="psi_loss"):
        _state_loss_at(0.0, labels, "huber")


def test_state_weights_scale_each_labels_term_and_bad_weights_are_refused() -> None:
    """Each label's term is its own error times its weight; equal weights of 1 are the plain mean."""
    labels = torch.from_numpy(normalise_labels(np.array([[4.0, 10.0, 90.0], [8.0, -20.0, -30.0]])))
    predicted = labels + torch.tensor([[0.1, -0.2, 0.3], [-0.3, 0.05, -0.1]], dtype=labels.dtype)
    squares = (predicted - labels).pow(2).mean(dim=0)  # per label, over frames
    plain = StateLoss()(predicted, labels)
    assert plain.item() == pytest.approx(squares.mean().item(), rel=1e-6)
    for index in range(3):
        weights = [1.0, 1.0, 1.0]
        weights[index] = 5.0
        weighted = StateLoss(weights=tuple(weights))(predicted, labels)
        assert weighted.item() == pytest.approx(plain.item() + 4.0 * squares[index].item() / 3.0, rel=1e-6)
    for bad in ((1.0, 2.0), (1.0, -1.0, 1.0), (0.0, 0.0, 0.0), (1.0, float("nan"), 1.0), (1.0,) * 5):
        with pytest.raises(ValueError, match="state weights"):
            StateLoss(weights=bad)
    with pytest.raises(ValueError, match="for a model of 3 labels"):
        StateLoss(weights=(1.0, 1.0, 1.0, 2.0))(predicted, labels)


def test_l1_theta_loss_pulls_on_a_small_azimuth_error_as_on_a_large_one() -> None:
    """theta's absolute error in place of its square, every other label's term unchanged; and its gradient the same
    size at 1 degree as at 20, where the square's is twenty times smaller."""
    labels = torch.from_numpy(normalise_labels(np.array([[6.0, 0.0, 90.0], [6.0, 5.0, -30.0]])))
    offsets = torch.tensor([[0.1, 0.0, 0.2], [-0.2, 0.0, -0.1]], dtype=labels.dtype)
    for degrees in (1.0, 20.0):
        predicted = labels + offsets
        predicted[:, 1] += degrees / ALPHA_DEG * torch.tensor([1.0, -1.0], dtype=labels.dtype)
        predicted.requires_grad_(True)
        errors = state_errors(predicted, labels).detach()
        plain, l1 = StateLoss()(predicted, labels), StateLoss(theta="l1")(predicted, labels)
        assert (l1 - plain).item() == pytest.approx(((errors[:, 1].abs() - errors[:, 1].pow(2)).mean() / 3).item())
        (gradient,) = torch.autograd.grad(l1, predicted)
        assert gradient[:, 1].abs().tolist() == pytest.approx([1 / 6, 1 / 6])  # 1 / (frames x labels), any size
        assert gradient[:, 2].tolist() == pytest.approx((2 * errors[:, 2] / 6).tolist())  # psi's square, as before
    with pytest.raises(ValueError, match="theta_loss 'huber'"):
        StateLoss(theta="huber")


def test_a_fourth_state_weight_scales_the_elevations_term() -> None:
    """A vertical model's elevation weighs 1 unless a fourth weight says otherwise."""
    raw = np.array([[4.0, 10.0, 90.0, 12.0], [8.0, -20.0, -30.0, -5.0]])
    labels = torch.from_numpy(normalise_labels(raw, VERTICAL_LABEL_NAMES))
    predicted = labels + torch.tensor([[0.1, -0.2, 0.3, 0.05], [-0.3, 0.05, -0.1, -0.2]], dtype=labels.dtype)
    squares = (predicted - labels).pow(2).mean(dim=0)
    plain = StateLoss()(predicted, labels)
    assert StateLoss(weights=(1.0, 1.0, 1.0, 1.0))(predicted, labels).item() == pytest.approx(plain.item(), rel=1e-6)
    weighted = StateLoss(weights=(1.0, 1.0, 1.0, 3.0))(predicted, labels)
    assert weighted.item() == pytest.approx(plain.item() + 2.0 * squares[3].item() / 4.0, rel=1e-6)


def test_images_become_channels_last_floats_in_minus_one_one_and_back(frames: np.ndarray) -> None:
    tensor = images_to_tensor(frames)
    assert tensor.shape == (4, 3, 64, 64) and tensor.dtype == torch.float32
    assert tensor.is_contiguous(memory_format=torch.channels_last)
    assert float(tensor.min()) >= -1.0 and float(tensor.max()) <= 1.0
    assert tensor[0, :, 5, 7].tolist() == pytest.approx((frames[0, 5, 7] / 127.5 - 1.0).tolist())
    np.testing.assert_array_equal(tensor_to_images(tensor), frames)


def test_n_z_below_three_is_refused() -> None:
    with pytest.raises(ValueError, match="n_z must be at least 3"):
        CMVAE(n_z=2)
