"""`swimm dataset`: the on-disk format, its labels and reproducibility."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.geometry import ALPHA_DEG, BETA_DEG, LABEL_NAMES, VERTICAL_LABEL_NAMES
from sim_service.dataset import POSE_NAMES, VERTICAL_RANGES, write_dataset
from swimm.cli import main


def load(directory):
    meta = json.loads((directory / "meta.json").read_text())
    arrays = {
        kind: np.concatenate([np.load(directory / f"{s}.{kind}.npy", mmap_mode="r") for s in meta["shards"]])
        for kind in ("images", "labels", "poses")
    }
    return meta, arrays


def test_dataset_format_labels_and_ranges(tmp_path):
    out = write_dataset(tmp_path / "ds", count=50, seed=3, shard_size=16, progress=False)
    meta, arrays = load(out)
    assert meta["format"] == "swimm-cmvae-dataset" and meta["version"] == 1
    assert meta["count"] == 50 and len(meta["shards"]) == 4  # 16 + 16 + 16 + 2
    assert meta["label_names"] == list(LABEL_NAMES) and meta["pose_names"] == list(POSE_NAMES)
    assert arrays["images"].shape == (50, 64, 64, 3) and arrays["images"].dtype == np.uint8
    d, theta, psi = arrays["labels"].T
    assert d.min() >= 2.0 and d.max() <= 10.0
    assert np.abs(theta).max() <= ALPHA_DEG + 1e-4 and np.abs(psi).max() <= 180.0
    # Labels agree with the poses: horizontal distance from the positions.
    poses = arrays["poses"]
    assert np.allclose(np.hypot(poses[:, 6] - poses[:, 0], poses[:, 7] - poses[:, 1]), d, atol=1e-4)


def test_same_seed_same_bytes_and_other_seed_differs(tmp_path):
    a = write_dataset(tmp_path / "a", count=8, seed=5, shard_size=8, progress=False)
    b = write_dataset(tmp_path / "b", count=8, seed=5, shard_size=4, progress=False)
    c = write_dataset(tmp_path / "c", count=8, seed=6, shard_size=8, progress=False)
    parallel = write_dataset(tmp_path / "p", count=8, seed=5, shard_size=3, progress=False, workers=2)
    assert np.array_equal(load(a)[1]["images"], load(b)[1]["images"])  # sharding does not change samples
    assert np.array_equal(load(a)[1]["images"], load(parallel)[1]["images"])  # nor do worker processes
    assert not np.array_equal(load(a)[1]["labels"], load(c)[1]["labels"])


def test_refuses_to_overwrite_and_cli_writes(tmp_path):
    assert main(["dataset", "--out", str(tmp_path / "cli"), "--count", "5", "--shard-size", "2"]) == 0
    assert json.loads((tmp_path / "cli" / "meta.json").read_text())["count"] == 5
    with pytest.raises(FileExistsError):
        write_dataset(tmp_path / "cli", count=5, seed=1, progress=False)


def test_a_paired_dataset_keeps_each_noisy_frames_clean_twin_with_the_same_labels(tmp_path):
    from sim_service.noise import NoiseSettings
    from sim_service.settings import WorldSettings

    noisy = WorldSettings(noise=NoiseSettings(preset="harsh", randomise=True))
    paired = write_dataset(tmp_path / "paired", count=12, seed=5, shard_size=5, world_settings=noisy,
                           progress=False, paired=True)  # fmt: skip
    plain = write_dataset(tmp_path / "plain", count=12, seed=5, shard_size=12, progress=False)
    meta, arrays = load(paired)
    _, clean_arrays = load(plain)
    clean = np.concatenate([np.load(paired / f"{s}.clean.npy") for s in meta["shards"]])
    assert meta["paired"] is True and clean.shape == arrays["images"].shape
    # The clean twins are the noise-free dataset of the same seed: same poses, same labels, same pixels.
    np.testing.assert_array_equal(clean, clean_arrays["images"])
    np.testing.assert_array_equal(arrays["labels"], clean_arrays["labels"])
    differences = np.abs(arrays["images"].astype(int) - clean).mean(axis=(1, 2, 3))
    assert (differences > 0).all() and differences.std() > 0.5  # every frame noisy, each by its own draw


def test_a_paired_dataset_without_noise_is_refused(tmp_path):
    with pytest.raises(ValueError, match="switch noise on"):
        write_dataset(tmp_path / "p", count=4, seed=1, progress=False, paired=True)
    assert not (tmp_path / "p").exists()


def _masks(directory):
    meta = json.loads((directory / "meta.json").read_text())
    return np.concatenate([np.load(directory / f"{s}.masks.npy") for s in meta["shards"]])


def test_masks_mark_exactly_the_pixels_the_dolphin_changes(tmp_path):
    """Each mask against its frame re-rendered with the dolphin 200 m behind the rover: the pixels that change."""
    from sim_service.settings import WorldSettings
    from sim_service.world import World

    out = write_dataset(tmp_path / "ds", count=10, seed=5, shard_size=4, progress=False, masks=True)
    meta, arrays = load(out)
    masks = _masks(out)
    assert meta["masks"] is True and masks.dtype == bool and masks.shape == (10, 64, 64)
    assert masks.any(axis=(1, 2)).all()
    world = World(WorldSettings())
    try:
        for image, mask, pose in zip(arrays["images"], masks, arrays["poses"], strict=True):
            rover, yaw = pose[:3].astype(float), np.radians(float(pose[5]))
            _, empty = world.place(rover, yaw, rover - 200.0 * np.array([np.cos(yaw), np.sin(yaw), 0.0]), 0.0)
            changed = (image != empty).any(axis=2)
            np.testing.assert_array_equal(changed, mask)
    finally:
        world.close()


def test_masks_do_not_depend_on_workers_or_noise_and_are_off_by_default(tmp_path):
    from sim_service.noise import NoiseSettings
    from sim_service.settings import WorldSettings

    one = write_dataset(tmp_path / "one", count=7, seed=5, shard_size=3, progress=False, masks=True)
    two = write_dataset(tmp_path / "two", count=7, seed=5, shard_size=3, progress=False, masks=True, workers=2)
    for shard in json.loads((one / "meta.json").read_text())["shards"]:
        for kind in ("images", "labels", "poses", "masks"):
            assert (one / f"{shard}.{kind}.npy").read_bytes() == (two / f"{shard}.{kind}.npy").read_bytes()
    noisy = WorldSettings(noise=NoiseSettings(preset="harsh", randomise=True))
    paired = write_dataset(tmp_path / "paired", count=7, seed=5, shard_size=7, world_settings=noisy,
                           progress=False, paired=True, masks=True)  # fmt: skip
    np.testing.assert_array_equal(_masks(paired), _masks(one))  # noise never moves the dolphin's pixels
    plain = write_dataset(tmp_path / "plain", count=3, seed=5, progress=False)
    assert "masks" not in json.loads((plain / "meta.json").read_text()) and not list(plain.glob("*.masks.npy"))


def test_a_vertical_dataset_labels_the_elevation_across_the_vertical_field_of_view(tmp_path):
    planar = write_dataset(tmp_path / "planar", count=40, seed=3, shard_size=40, progress=False)  # the same draws
    out = write_dataset(tmp_path / "vertical", count=40, seed=3, shard_size=16, progress=False, ranges=VERTICAL_RANGES)
    meta, arrays = load(out)
    assert meta["label_names"] == list(VERTICAL_LABEL_NAMES) and arrays["labels"].shape == (40, 4)
    assert meta["ranges"]["elevation_deg"] == pytest.approx(BETA_DEG)
    d, theta, _, elevation = arrays["labels"].T
    assert d.min() >= 2.0 and d.max() <= 10.0 and np.abs(theta).max() <= ALPHA_DEG + 1e-4
    # Anywhere in the vertical view, above and below, where the planar frames keep within a few degrees.
    assert elevation.min() < -BETA_DEG / 2 and elevation.max() > BETA_DEG / 2
    assert np.abs(elevation).max() <= BETA_DEG + 1e-3
    # The target within its depth band; the planar frames' (the same seed's poses but for depth) keep level.
    poses = arrays["poses"]
    planar_poses = load(planar)[1]["poses"]
    assert np.allclose(planar_poses[:, [0, 1, 5, 6, 7, 11]], poses[:, [0, 1, 5, 6, 7, 11]], atol=1e-3)
    assert np.abs(planar_poses[:, 8] - planar_poses[:, 2]).max() <= 0.5 + 1e-4
    assert (-poses[:, 8] >= VERTICAL_RANGES.target_depth[0] - 1e-4).all()
    assert (-poses[:, 8] <= VERTICAL_RANGES.target_depth[1] + 1e-4).all()
