"""The pod detector: labels from a real pod dataset's poses, a short real training, and the encoder it makes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from encoder_service.augment import CONTRAST_LOG_RANGE, AugmentSettings, contrast
from encoder_service.inference import DEFAULT_CHECKPOINT, LatentEncoder, check_encoder_file, open_encoder
from encoder_service.model import images_to_tensor, read_checkpoint
from encoder_service.pod_detector import (
    MIN_TARGET_PIXELS,
    PodDetector,
    decode,
    dolphin_points,
    heatmap_targets,
    seen_dolphins,
    to_pixels,
)
from encoder_service.pod_detector_train import (
    TrainDetectorSettings,
    batch,
    check,
    join_datasets,
    load_pod_dataset,
    run,
    split_rows,
)
from encoder_service.pod_encoder import PodEncoder, read_detector
from encoder_service.service import EncoderSettings
from encoder_service.service import check as check_encoder
from services.detections import from_pixels, rover_azimuth
from services.pod_tracker import STATE_SIZE
from tests.encoder.pod_testdata import render_pod_dataset


@pytest.fixture(scope="module")
def pod(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small dataset of a pod of 3, with masks."""
    return render_pod_dataset(tmp_path_factory.mktemp("detector") / "pod", count=64, shard_size=32)


@pytest.fixture(scope="module")
def detector(pod: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("detector") / "detector.pt"
    settings = TrainDetectorSettings(dataset=[str(pod)], out=str(out), epochs=2, batch_size=16, val_frames=16)
    assert run(settings) == 0
    return out


def test_pixels_and_rays_agree() -> None:
    points = np.array([[6.0, 1.0, -0.5], [3.0, -2.0, 0.4], [9.0, 0.0, 0.0]])
    x, y = to_pixels(points, 64).T
    assert (x[2], y[2]) == pytest.approx((32.0, 32.0))  # on the axis: the image centre
    azimuth, elevation = from_pixels(x, y, 64)
    np.testing.assert_allclose(azimuth, np.degrees(np.arctan2(points[:, 1], points[:, 0])), atol=1e-9)
    np.testing.assert_allclose(elevation, np.degrees(np.arctan2(points[:, 2], np.hypot(*points[:, :2].T))), atol=1e-9)


def test_the_labels_are_the_datasets_own(pod: Path) -> None:
    """The target's distance and the azimuth the camera's ray gives, moved to the rover's centre, are the stored
    labels; the target's centre falls inside its own mask in most frames that show it."""
    data = load_pod_dataset(pod)
    labels = np.concatenate([np.load(path) for path in sorted(pod.glob("*.labels.npy"))])
    masks = np.concatenate([np.load(path) for path in sorted(pod.glob("*.masks.npy"))])
    np.testing.assert_allclose(data["distances"][:, 0], labels[:, 0], atol=1e-4)
    np.testing.assert_allclose(data["azimuths"][:, 0], labels[:, 1], atol=1e-3)
    points = dolphin_points(data["poses"].astype(float), data["companions"].astype(float))
    camera_azimuth = np.degrees(np.arctan2(points[:, 0, 1], points[:, 0, 0]))
    np.testing.assert_allclose(rover_azimuth(camera_azimuth, data["distances"][:, 0]), labels[:, 1], atol=1e-3)
    shown = data["seen"][:, 0]
    assert shown.sum() >= 20
    x, y = np.clip(data["pixels"][:, 0].astype(int), 0, 63).T
    on_mask = np.array([masks[i, max(y[i] - 2, 0) : y[i] + 3, max(x[i] - 2, 0) : x[i] + 3].any() for i in range(64)])
    assert on_mask[shown].mean() > 0.8


def test_each_seen_dolphin_peaks_at_its_cell() -> None:
    pixels = np.array([[[10.3, 20.9], [50.0, 33.0]]])
    seen, ignored = np.array([[True, False]]), np.array([[False, True]])
    targets = heatmap_targets(pixels, np.array([[5.0, 3.0]]), seen, ignored, 64, 2)
    assert targets["heat"][0, 10, 5] == 1.0 and targets["centre"].sum() == 1
    assert targets["regress"][0, :, 10, 5] == pytest.approx([0.15, 0.45, np.log(5.0)], abs=1e-6)
    assert targets["skip"][0, 16, 25] and not targets["skip"][0, 10, 5]  # the hidden one: neither taught nor punished


def test_a_hidden_companion_is_not_seen(pod: Path) -> None:
    data = load_pod_dataset(pod)
    points = dolphin_points(data["poses"].astype(float), data["companions"].astype(float))
    seen, ignored = seen_dolphins(points, data["target_pixels"])
    assert not (seen & ignored).any()
    assert ignored.any()  # the dataset's sight-line companions hide some


def test_decode_reads_a_peak_back() -> None:
    heat = torch.full((1, 1, 32, 32), -9.0)
    heat[0, 0, 10, 16] = 4.0
    regression = torch.zeros((1, 3, 32, 32))
    regression[0, :, 10, 16] = torch.tensor([0.5, 0.5, float(np.log(6.0))])
    (frame,) = decode(heat, regression, 0.3, 64, 2)
    assert len(frame) == 1
    assert frame.distance[0] == pytest.approx(6.0)
    assert frame.azimuth[0] == pytest.approx(rover_azimuth(from_pixels(33.0, 21.0, 64)[0], 6.0))


def test_training_writes_an_encoder_the_loaders_take(detector: Path) -> None:
    encoder = open_encoder(detector)
    assert isinstance(encoder, PodEncoder) and encoder.tracks
    with pytest.raises(ValueError, match="pod detector, not a CMVAE"):
        read_checkpoint(detector)
    with pytest.raises(ValueError, match="pod detector"):
        LatentEncoder(detector)
    check_encoder(EncoderSettings(checkpoint=str(detector)))  # `swimm encoder` serves it (protocol 6's prior)
    check_encoder(EncoderSettings(checkpoint=str(detector), engine="onnx"))
    with pytest.raises(ValueError, match=r"pod detector, which runs on the cpu only .* on device 'cuda'"):
        check_encoder_file(detector, "torch", "cuda")
    summary = detector.with_suffix(".json")
    assert summary.is_file() and "history" in summary.read_text()


def test_the_onnx_engine_reads_as_torch_does(detector: Path, pod: Path) -> None:
    """The detector exported to ONNX gives the torch network's heat and regression within 1e-4 on real frames,
    and the same target latents and tracker states over a run of frames."""
    images = load_pod_dataset(pod)["images"][:12]
    torch_encoder, onnx_encoder = PodEncoder(detector), open_encoder(detector, engine="onnx")
    assert isinstance(onnx_encoder, PodEncoder) and onnx_encoder.engine == "onnx"
    frames = images_to_tensor(images)
    with torch.no_grad():
        for ours, theirs in zip(onnx_encoder._detect(frames), torch_encoder.model(frames), strict=True):
            np.testing.assert_allclose(ours.numpy(), theirs.numpy(), atol=1e-4)
    states = {"torch": None, "onnx": None}
    for frame in images:
        (mu_t, _, states["torch"]) = torch_encoder.track(frame[None], states["torch"])
        (mu_o, _, states["onnx"]) = onnx_encoder.track(frame[None], states["onnx"])
        np.testing.assert_allclose(mu_o, mu_t, atol=1e-4)
        np.testing.assert_allclose(states["onnx"], states["torch"], atol=1e-4)


def test_the_encoder_carries_its_tracker_state(detector: Path, pod: Path) -> None:
    encoder = open_encoder(detector)
    images = load_pod_dataset(pod)["images"][:4]
    mu, logvar, state = encoder.track(images)
    assert mu.shape == (4, encoder.n_z) and state.shape == (4, STATE_SIZE)
    distance, azimuth, _ = encoder.decode_state(mu)
    assert np.all((distance >= 2.0) & (distance <= 10.0)) and np.all(np.abs(azimuth) <= 45.0)
    again, _, _ = encoder.track(images, state)
    assert again.shape == mu.shape


def test_bad_settings_are_refused_by_flag(pod: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--stride 3"):
        check(TrainDetectorSettings(dataset=[str(pod)], stride=3, out=str(tmp_path / "d.pt")))
    with pytest.raises(FileNotFoundError, match="no meta.json"):
        check(TrainDetectorSettings(dataset=[str(tmp_path)], out=str(tmp_path / "d.pt")))
    with pytest.raises(ValueError, match="--augment-shafts is a share of frames"):
        check(TrainDetectorSettings(dataset=[str(pod)], augment_shafts=1.5, out=str(tmp_path / "d.pt")))
    with pytest.raises(ValueError, match="--augment-blur is a share of frames"):
        check(TrainDetectorSettings(dataset=[str(pod)], augment_blur=1.01, out=str(tmp_path / "d.pt")))
    with pytest.raises(ValueError, match="--augment-contrast is a share of frames"):
        check(TrainDetectorSettings(dataset=[str(pod)], augment_contrast=-0.5, out=str(tmp_path / "d.pt")))
    (tmp_path / "d.pt").write_bytes(b"")
    with pytest.raises(FileExistsError, match="--overwrite"):
        check(TrainDetectorSettings(dataset=[str(pod)], out=str(tmp_path / "d.pt")))


def test_augmentation_changes_the_look_not_the_labels(pod: Path) -> None:
    data = load_pod_dataset(pod)
    rows = np.arange(8)
    plain_frames, plain_targets = batch(data, rows, 2)
    rng = np.random.default_rng(0)
    jitter = AugmentSettings(augment=1.0, augment_shafts=1.0, augment_blur=1.0)

    def photometric(images: np.ndarray, masks: np.ndarray) -> np.ndarray:
        return jitter.augmented(contrast(images, masks, rng, 1.0), rng)

    frames, targets = batch(data, rows, 2, photometric=photometric)
    assert not torch.equal(frames, plain_frames)
    assert all(torch.equal(targets[name], plain_targets[name]) for name in plain_targets)


def test_contrast_moves_the_dolphin_from_its_water_and_nothing_else(pod: Path) -> None:
    """In even water the dolphin's every pixel moves from the water by one factor a frame, drawn from the seed
    within the range; on real frames pixels well clear of its mask keep their values."""
    frames = np.empty((8, 64, 64, 3), np.uint8)
    frames[:] = (110, 120, 130)
    masks = np.zeros((8, 64, 64), bool)
    for mask in masks:
        cv2.ellipse(mask.view(np.uint8), (32, 30), (12, 4), 10, 0, 360, 1, -1)
    frames[masks] = (150, 160, 170)
    changed = contrast(frames, masks, np.random.default_rng(3), 1.0)
    np.testing.assert_array_equal(changed, contrast(frames, masks, np.random.default_rng(3), 1.0))
    np.testing.assert_array_equal(contrast(frames, masks, np.random.default_rng(3), 0.0), frames)
    inside = cv2.erode(masks[0].view(np.uint8), np.ones((5, 5), np.uint8)) > 0
    factors = (changed[:, inside].astype(float) - (110, 120, 130)) / 40.0
    per_frame = factors.reshape(8, -1)
    np.testing.assert_allclose(
        per_frame, np.broadcast_to(per_frame[:, :1], per_frame.shape), atol=0.02
    )  # one factor a frame, up to rounding
    size = np.abs(per_frame)
    assert np.all((size > np.exp(-CONTRAST_LOG_RANGE) - 0.02) & (size < np.exp(CONTRAST_LOG_RANGE) + 0.02))
    assert np.ptp(per_frame[:, 0]) > 0.3  # drawn anew for each frame
    flipped = contrast(np.repeat(frames, 8, axis=0), np.repeat(masks, 8, axis=0), np.random.default_rng(4), 1.0)
    turned = (flipped[:, inside][:, :, 0].astype(float) < 110).all(axis=1)  # darker than the water: turned round
    assert 0.1 < turned.mean() < 0.5
    data = load_pod_dataset(pod)
    rows = np.flatnonzero(data["target_pixels"] >= 40)[:6]
    real = contrast(data["images"][rows], data["masks"][rows], np.random.default_rng(3), 1.0)
    for before, after, mask in zip(data["images"][rows], real, data["masks"][rows], strict=True):
        clear = cv2.dilate(mask.view(np.uint8), np.ones((7, 7), np.uint8)) == 0
        np.testing.assert_array_equal(after[clear], before[clear])
        assert not np.array_equal(after, before)


def test_a_lone_dolphins_dataset_trains_beside_a_pods(pod: Path, tmp_path: Path) -> None:
    """A lone dolphin's frames (no companions) label the target alone, seen where its mask shows it; joined with a
    pod's, the lone frames' missing companions are never seen, and each dataset gives frames to validation."""
    folder = render_pod_dataset(tmp_path / "alone", count=16, shard_size=16, pod_size=1)
    alone = load_pod_dataset(folder)
    assert alone["companions"].shape == (16, 0, 6) and alone["seen"].shape == (16, 1)
    seen = alone["seen"][:, 0]
    assert seen.sum() >= 8 and np.all(alone["target_pixels"][seen] >= MIN_TARGET_PIXELS)
    joined = join_datasets([alone, load_pod_dataset(pod)])
    assert joined["seen"].shape == (80, 3) and joined["companions"].shape == (80, 2, 6)
    assert np.array_equal(joined["seen"][:16, 0], seen) and not joined["seen"][:16, 1:].any()
    train, val = split_rows([16, 64], 9)
    assert list(val) == [11, 12, 13, 14, 15, *range(76, 80)] and len(train) == 80 - 9
    with pytest.raises(ValueError, match="--val-frames 40: a dataset of 16 frames cannot hold out 20"):
        split_rows([16, 64], 40)
    out = tmp_path / "both.pt"
    assert run(TrainDetectorSettings(dataset=[str(folder), str(pod)], out=str(out), epochs=1, batch_size=16,
                                     val_frames=8)) == 0  # fmt: skip
    (scores,) = read_detector(out)["history"]
    assert 0.0 <= scores["target_recall"] <= 1.0 and np.isfinite(scores["extra_peaks_per_frame"])


def test_a_run_from_init_starts_from_its_weights(detector: Path, pod: Path, tmp_path: Path) -> None:
    out = tmp_path / "again.pt"
    settings = TrainDetectorSettings(dataset=[str(pod)], out=str(out), epochs=1, batch_size=16, val_frames=16,
                                     lr=1e-12, init=str(detector))  # fmt: skip
    assert run(settings) == 0
    started, again = (torch.load(path, weights_only=True)["state_dict"] for path in (detector, out))
    fresh = PodDetector().state_dict()
    for name, weights in started.items():
        if weights.is_floating_point() and "running" not in name:  # batch norm's statistics move at any lr
            torch.testing.assert_close(again[name], weights, atol=1e-6, rtol=0)
    assert any(not torch.equal(fresh[name], started[name]) for name in fresh)


def test_a_bad_init_is_refused_by_flag(detector: Path, pod: Path, tmp_path: Path) -> None:
    def settings(**overrides) -> TrainDetectorSettings:
        return TrainDetectorSettings(dataset=[str(pod)], out=str(tmp_path / "d.pt"), **overrides)

    with pytest.raises(FileNotFoundError, match="--init .*missing.pt does not exist"):
        check(settings(init=str(tmp_path / "missing.pt")))
    with pytest.raises(ValueError, match="--init .*cmvae.pt is not a swimm-pod-detector checkpoint"):
        check(settings(init=str(DEFAULT_CHECKPOINT)))
    with pytest.raises(ValueError, match="--stride 4 differs from --init .*'s 2"):
        check(settings(init=str(detector), stride=4))


def test_the_detector_runs_both_strides() -> None:
    for stride in (2, 4):
        heat, regression = PodDetector(stride=stride)(torch.rand(2, 3, 64, 64))
        assert heat.shape == (2, 1, 64 // stride, 64 // stride) and regression.shape[1] == 3
