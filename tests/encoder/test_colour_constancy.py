"""Colour constancy in the encoder and the photometric jitter of its training frames: real torch, real checkpoints."""

from __future__ import annotations

import io
import math
from pathlib import Path

import cv2
import numpy as np
import onnxruntime
import pytest
import torch

from encoder_service.augment import (
    BANDS_MAX,
    DEFOCUS_SIGMA,
    SHAFT_TINT,
    bands,
    defocus,
    fan_from,
    fans,
    jitter,
    shafts,
)
from encoder_service.inference import LatentEncoder
from encoder_service.model import (
    CMVAE,
    LOCAL_WINDOW,
    REFERENCE_MEAN,
    frame_mean,
    images_to_tensor,
    load_model,
    make_checkpoint,
    with_prior,
)
from encoder_service.train import TrainEncoderSettings, load_init_weights, run
from tests.encoder.cmvae_testdata import write_dataset


def test_a_channel_norm_encoder_reads_a_tinted_and_dimmed_frame_as_the_original() -> None:
    """A per-channel gain over the whole frame (a water tint, brighter or dimmer light) is removed before the first
    convolution, so the latent does not move; without the norm it does."""
    torch.manual_seed(0)
    frames = images_to_tensor(np.random.default_rng(1).integers(40, 200, (4, 64, 64, 3), dtype=np.uint8))
    gain = torch.tensor([0.5, 1.3, 0.8]).view(1, 3, 1, 1)
    tinted = (frames + 1.0) * gain - 1.0  # the gain acts on light intensity, 0 at black
    for input_norm, moves in (("channel", False), ("none", True)):
        model = CMVAE(input_norm=input_norm).eval()
        with torch.no_grad():
            mu, _ = model.encode(frames)
            mu_tinted, _ = model.encode(tinted)
        assert (not torch.allclose(mu, mu_tinted, atol=1e-4)) == moves, input_norm


def _water_with_a_dolphin_under_a_shaft() -> tuple[torch.Tensor, torch.Tensor]:
    """A water-coloured frame with a dark blob, and the same frame under a wide band of added light."""
    water = np.broadcast_to(np.array([27, 73, 87], dtype=np.uint8), (1, 64, 64, 3)).copy()
    water[:, 28:36, 24:40] = (60, 60, 60)
    frame = images_to_tensor(water)
    columns = torch.linspace(0.0, 1.0, 64).view(1, 1, 1, 64)
    lit = (frame + 0.6 * columns).clamp(-1.0, 1.0)  # light growing across the frame, as a shaft's wedge does
    return frame, lit


def test_a_local_norm_encoder_evens_out_light_across_the_frame() -> None:
    """Light added across the frame is gone from the water after the local norm (away from the borders, whose
    neighbourhoods are padded, and from the dolphin's), where the white balance alone keeps it; the dolphin still
    stands out from the water."""
    frame, lit = _water_with_a_dolphin_under_a_shaft()
    water = torch.ones(1, 1, 64, 64, dtype=torch.bool)
    water[..., 20:44, 16:48] = False  # the dolphin and its neighbourhood
    water[..., :LOCAL_WINDOW, :] = water[..., -LOCAL_WINDOW:, :] = False
    water[..., :LOCAL_WINDOW] = water[..., -LOCAL_WINDOW:] = False
    water = water.expand(1, 3, 64, 64)
    changes = {}
    for input_norm in ("channel", "local"):
        normalise = CMVAE(input_norm=input_norm).encoder.normalise
        changes[input_norm] = (normalise(lit) - normalise(frame))[water].abs().max().item()
        seen = normalise(lit)
        assert (seen[..., 30:34, 28:36].mean() - seen[..., 30:34, 44:50].mean()).abs() > 0.02, input_norm
    assert changes["local"] < 1e-4 < 0.05 < changes["channel"], changes


def test_a_light_norm_encoder_keeps_the_light_the_local_norm_takes_away_beside_the_evened_frame() -> None:
    """Channels 0 to 2 are the local norm's; channels 3 to 5 carry the light added across the frame, coarse (no
    sharper than the neighbourhood), and with the evened frame they give back the white-balanced frame."""
    frame, lit = _water_with_a_dolphin_under_a_shaft()
    light = CMVAE(input_norm="light").encoder.normalise
    local = CMVAE(input_norm="local").encoder.normalise
    seen, seen_lit = light(frame), light(lit)
    assert seen.shape == (1, 6, 64, 64)
    torch.testing.assert_close(seen[:, :3], local(frame))
    # across the water above the dolphin, the light channels are flat in the frame and rise with the added light
    for image, rise in ((seen, 0.0), (seen_lit, 0.3)):
        water_rows = image[:, 3:, :10]
        assert (water_rows[..., -1] - water_rows[..., 0]).mean().item() == pytest.approx(rise, abs=0.1)
    assert seen[:, 3:].diff(dim=-1).abs().max() < 0.2 * seen[:, :3].diff(dim=-1).abs().max()  # the dolphin's edges
    # evened + local = the frame + its mean, so in [0, 1] intensity the two halves sum to the white balance's
    # frame plus the balanced frame mean, which is the target
    target = torch.tensor(REFERENCE_MEAN).view(1, 3, 1, 1)
    halves = (seen[:, :3] + 1) / 2 + (seen[:, 3:] + 1) / 2
    balanced = (CMVAE(input_norm="channel").encoder.normalise(frame) + 1) / 2
    torch.testing.assert_close(halves, balanced + target, rtol=0, atol=2e-3)


@pytest.mark.parametrize("input_norm", ["local", "light"])
def test_a_local_or_light_norm_encoder_runs_the_same_in_onnx(tmp_path: Path, input_norm: str) -> None:
    torch.manual_seed(3)
    path = tmp_path / "local.pt"
    torch.save(make_checkpoint(CMVAE(input_norm=input_norm), beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    frames = np.random.default_rng(4).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    torch_mu, _ = LatentEncoder(path, threads=1).encode(frames)
    onnx_mu, _ = LatentEncoder(path, engine="onnx").encode(frames)
    np.testing.assert_allclose(onnx_mu, torch_mu, atol=1e-4)


@pytest.mark.parametrize("input_norm", ["channel", "local", "light"])
def test_the_exported_norm_equals_torchs_in_dark_water(input_norm: str) -> None:
    """A dark frame's white-balance gain is large, so the frame mean's error is multiplied into every pixel: the
    exported norm keeps to float rounding of torch's (a one-pass ONNX mean of the frame erred 2e-5 here), and
    torch's own path is the plain mean it always was."""
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 40, (8, 64, 64, 3), dtype=np.uint8)
    frames[:, 24:40, 20:44] = rng.integers(60, 120, (8, 16, 24, 3))  # something brighter in the dark water
    images = images_to_tensor(frames)
    assert torch.equal(frame_mean(images), images.mean(dim=(2, 3), keepdim=True))
    normalise = CMVAE(input_norm=input_norm).encoder.normalise.eval()
    graph = io.BytesIO()
    torch.onnx.export(normalise, (images[:1],), graph, input_names=["x"], output_names=["y"], dynamo=False,
                      dynamic_axes={"x": {0: "n"}, "y": {0: "n"}})  # fmt: skip
    exported = onnxruntime.InferenceSession(graph.getvalue(), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        np.testing.assert_allclose(exported.run(None, {"x": images.numpy()})[0], normalise(images).numpy(), atol=5e-6)


def test_the_input_norm_travels_in_the_checkpoint(tmp_path: Path) -> None:
    path = tmp_path / "cmvae.pt"
    torch.save(make_checkpoint(CMVAE(input_norm="channel"), beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    model, checkpoint = load_model(path)
    assert checkpoint["config"]["input_norm"] == "channel" and model.encoder.input_norm == "channel"
    with pytest.raises(ValueError, match="input_norm must be one of none, channel, local, light"):
        CMVAE(input_norm="retinex")


def _changed_share(augment, frames: np.ndarray) -> list[np.ndarray]:
    """The frames ``augment`` changed at share 0.5, after checking it is seeded, keeps uint8 and changes about
    half of them (and none at share 0)."""
    first = augment(frames, np.random.default_rng(5), 0.5)
    np.testing.assert_array_equal(first, augment(frames, np.random.default_rng(5), 0.5))
    assert first.dtype == np.uint8 and first.shape == frames.shape
    changed = [image for image, before in zip(first, frames, strict=True) if not np.array_equal(image, before)]
    assert 0.35 < len(changed) / len(frames) < 0.65
    np.testing.assert_array_equal(augment(frames, np.random.default_rng(5), 0.0), frames)
    return changed


def test_jitter_is_seeded_touches_only_its_share_and_keeps_uint8() -> None:
    _changed_share(jitter, np.random.default_rng(2).integers(0, 256, (200, 64, 64, 3), dtype=np.uint8))


def test_bands_are_seeded_translucent_and_touch_only_their_share() -> None:
    for image in _changed_share(bands, np.full((200, 64, 64, 3), 40, dtype=np.uint8)):
        untouched = np.mean(np.all(image == 40, axis=-1))
        assert 0.0 < untouched < 1.0  # a band crosses part of the frame, never all of it
        # each band is at most half opaque, so where they overlap the frame still shows through
        assert np.abs(image.astype(int) - 40).max() <= (1 - 0.5**BANDS_MAX) * 255 + 1


def test_shafts_are_seeded_pale_near_parallel_and_touch_only_their_share() -> None:
    frames = np.full((200, 64, 64, 3), 40, dtype=np.uint8)
    lit = _changed_share(shafts, frames)
    for image in lit:
        brightness = image.astype(int).mean(axis=-1)
        assert 0.0 < np.mean(brightness > 40) < 1.0 and brightness.min() >= 40 - SHAFT_TINT  # light falls on part
    # one direction per frame: their edges line up far more than those of bands at random angles
    banded = bands(frames, np.random.default_rng(5), 1.0)
    assert np.mean([_edge_coherence(image) for image in lit]) > np.mean([_edge_coherence(i) for i in banded]) + 0.1


def test_fans_are_seeded_pale_rays_from_one_point_and_touch_only_their_share() -> None:
    frames = np.full((200, 64, 64, 3), 40, dtype=np.uint8)
    for image in _changed_share(fans, frames):
        brightness = image.astype(int).mean(axis=-1)
        assert 0.0 < np.mean(brightness > 40) < 1.0 and brightness.min() >= 40 - SHAFT_TINT
    # rays from one point: each covers the same bearings seen from it at any distance, as a wedge from it does
    bearings = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    for seed in range(5):
        lit = fan_from(frames[0], np.random.default_rng(seed), (32.0, 32.0)).astype(int).mean(axis=-1) > 41
        near, far = ([lit[np.rint(32 + radius * np.sin(b)).astype(int), np.rint(32 + radius * np.cos(b)).astype(int)]
                      for b in bearings] for radius in (12, 28))  # fmt: skip
        assert np.any(near) and np.mean(np.equal(near, far)) > 0.9


def test_defocus_spreads_a_point_by_its_drawn_sigma_and_touches_only_its_share() -> None:
    frames = np.zeros((200, 64, 64, 3), dtype=np.uint8)
    frames[:, 32, 32] = 255
    for image in _changed_share(defocus, frames):
        spot = image[..., 0].astype(float)
        rows = np.arange(64)[:, None]
        sigma = np.sqrt((spot * (rows - 32) ** 2).sum() / spot.sum())  # the blur's spread about the point
        assert DEFOCUS_SIGMA[0] - 0.25 < sigma < DEFOCUS_SIGMA[1] + 0.25 and spot.sum() == pytest.approx(255, rel=0.2)


def _edge_coherence(image: np.ndarray) -> float:
    """1 when every edge in the frame runs one way, near 0 when they run every way (the structure tensor's)."""
    brightness = image.astype(np.float32).mean(axis=-1)
    gradients = cv2.Sobel(brightness, cv2.CV_32F, 1, 0) + 1j * cv2.Sobel(brightness, cv2.CV_32F, 0, 1)
    return float(abs(np.sum(gradients**2)) / (np.sum(np.abs(gradients) ** 2) + 1e-9))


def test_a_run_with_norm_and_jitter_trains_and_refuses_bad_values(tmp_path: Path) -> None:
    dataset = write_dataset(tmp_path / "data", count=64, seed=3, shard_size=32)
    out = tmp_path / "run"
    settings = TrainEncoderSettings(dataset=[str(dataset)], out=str(out), epochs=1, val_fraction=0.25, device="cpu",
                                    tensorboard=False, input_norm="channel", augment=0.5,
                                    augment_bands=0.5, augment_shafts=0.5, augment_fans=0.5)  # fmt: skip
    assert run(settings) == 0
    best = torch.load(out / "best.pt", weights_only=True)
    assert best["config"]["input_norm"] == "channel" and math.isfinite(best["val_loss"])
    refusals = (
        ({"augment": 1.5}, "--augment is a share"),
        ({"augment_bands": -0.1}, "--augment-bands is a share"),
        ({"augment_shafts": 2.0}, "--augment-shafts is a share"),
        ({"augment_fans": 1.2}, "--augment-fans is a share"),
        ({"input_norm": "x"}, "--input-norm"),
    )
    for change, message in refusals:
        with pytest.raises(ValueError, match=message):
            run(TrainEncoderSettings(dataset=[str(dataset)], out=str(tmp_path / "bad"), **change))


@pytest.mark.parametrize(
    ("start", "started"),
    [
        ({"input_norm": "local"}, {"input_norm": "light"}),
        ({"input_norm": "light"}, {"input_norm": "light", "track": True}),
    ],
)
def test_a_model_started_from_one_without_the_light_or_prior_reads_as_it(
    tmp_path: Path, start: dict, started: dict
) -> None:
    """Weights go to the input channels of the same name, the new ones through zeros: a light model started from a
    local one, or a light tracker from a light model (its prior between the colours and the light), starts as it."""
    torch.manual_seed(6)
    path = tmp_path / "start.pt"
    original = CMVAE(**start).eval()
    torch.save(make_checkpoint(original, beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    model = CMVAE(**started).eval()
    load_init_weights(model, str(path), n_z=10)
    frames = images_to_tensor(np.random.default_rng(7).integers(0, 256, (4, 64, 64, 3), dtype=np.uint8))
    with torch.no_grad():
        inputs = with_prior(frames, torch.linspace(-20, 20, 4)) if model.tracks else frames
        torch.testing.assert_close(model.encode(inputs), original.encode(frames), rtol=1e-5, atol=1e-5)
