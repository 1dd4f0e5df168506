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


def _stacked(directory, kind):
    """One per-sample array of a dataset (``kind``: masks, others, companions, ...), its shards concatenated."""
    meta = json.loads((directory / "meta.json").read_text())
    return np.concatenate([np.load(directory / f"{s}.{kind}.npy") for s in meta["shards"]])


def test_masks_mark_exactly_the_pixels_the_dolphin_changes(tmp_path):
    """Each mask against its frame re-rendered with the dolphin 200 m behind the rover: the pixels that change."""
    from sim_service.settings import WorldSettings
    from sim_service.world import World

    out = write_dataset(tmp_path / "ds", count=10, seed=5, shard_size=4, progress=False, masks=True)
    meta, arrays = load(out)
    masks = _stacked(out, "masks")
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
    # Noise never moves the dolphin's pixels.
    np.testing.assert_array_equal(_stacked(paired, "masks"), _stacked(one, "masks"))
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


def pod_settings(size: int):
    from sim_service.settings import DolphinSettings, WorldSettings

    return WorldSettings(dolphin=DolphinSettings(pod_size=size))


def _shard_files(directory):
    return {path.name: path.read_bytes() for path in sorted(directory.iterdir())}


def dolphins_in_camera(directory):
    """Every sample's dolphins (the target first) in the camera's (forward, left, up) frame, (n, pod size, 3), from
    the written poses; a sample's rover is level, so its yaw alone turns the world into its frame."""
    from services.geometry import CAMERA_ABOVE_M, CAMERA_AHEAD_M

    poses = _stacked(directory, "poses").astype(float)
    bodies = np.concatenate([poses[:, None, 6:9], _stacked(directory, "companions")[..., :3]], axis=1)
    offset = bodies - poses[:, None, :3]
    yaw = np.radians(poses[:, 5])[:, None]
    ahead = np.cos(yaw) * offset[..., 0] + np.sin(yaw) * offset[..., 1]
    left = -np.sin(yaw) * offset[..., 0] + np.cos(yaw) * offset[..., 1]
    return np.stack([ahead - CAMERA_AHEAD_M, left, offset[..., 2] - CAMERA_ABOVE_M], axis=-1)


def test_a_pod_dataset_replays_from_its_seed_whatever_the_workers_and_keeps_the_targets_labels(tmp_path):
    one = write_dataset(tmp_path / "one", count=7, seed=5, shard_size=3, world_settings=pod_settings(4),
                        progress=False, masks=True)  # fmt: skip
    two = write_dataset(tmp_path / "two", count=7, seed=5, shard_size=3, world_settings=pod_settings(4),
                        progress=False, masks=True, workers=2)  # fmt: skip
    assert _shard_files(one) == _shard_files(two)
    meta = json.loads((one / "meta.json").read_text())
    assert meta["pod"] == {"size": 4, "sight_share": 0.25, "others": True}
    assert _stacked(one, "companions").shape == (7, 3, 6) and _stacked(one, "others").shape == (7, 64, 64)
    # The companions draw from a generator of their own: the target's poses and labels are the lone dolphin's.
    single = write_dataset(tmp_path / "single", count=7, seed=5, shard_size=7, progress=False)
    for kind in ("labels", "poses"):
        np.testing.assert_array_equal(_stacked(one, kind), _stacked(single, kind))
    other_seed = write_dataset(tmp_path / "six", count=7, seed=6, shard_size=7, world_settings=pod_settings(4),
                               progress=False)  # fmt: skip
    assert not np.array_equal(_stacked(one, "companions"), _stacked(other_seed, "companions"))


def test_a_pod_of_one_is_the_dataset_written_without_the_flag(tmp_path):
    plain, pod = tmp_path / "plain", tmp_path / "pod"
    flags = ["--count", "5", "--seed", "5", "--shard-size", "3", "--masks"]
    assert main(["dataset", "--out", str(plain), *flags]) == 0
    assert main(["dataset", "--out", str(pod), *flags, "--dolphin-pod-size", "1", "--sight-share", "1"]) == 0
    assert _shard_files(plain) == _shard_files(pod)
    assert "pod" not in json.loads((pod / "meta.json").read_text())


def test_a_pod_frame_shows_companions_and_the_target_mask_only_what_is_seen_of_the_target(tmp_path):
    pod = write_dataset(tmp_path / "pod", count=24, seed=3, shard_size=24, world_settings=pod_settings(4),
                        progress=False, masks=True)  # fmt: skip
    single = write_dataset(tmp_path / "single", count=24, seed=3, shard_size=24, progress=False, masks=True)
    target, others, alone = _stacked(pod, "masks"), _stacked(pod, "others"), _stacked(single, "masks")
    # The same poses and scenes: the companions are all the pod changes, and they change their own pixels (but the
    # odd one where a look-alike companion in front of the target has the target's very colour).
    changed = (_stacked(pod, "images") != _stacked(single, "images")).any(axis=3)
    assert (changed <= others).all() and (others & ~changed).sum() <= 0.01 * others.sum()
    # The target's mask is the lone dolphin's less what companions in front of it hide, and never a companion's.
    assert not (target & others).any() and not (target & ~alone).any()
    assert ((alone & ~target) <= others).all()
    assert (others.sum(axis=(1, 2)) > 0).mean() >= 0.5  # companions in view in most frames


def test_a_pod_dataset_puts_companions_in_front_of_the_target_and_nearer_the_image_centre(tmp_path):
    from services.identity import hidden, off_axis_deg

    shares = {}
    for share in (0.0, 1.0):
        out = write_dataset(tmp_path / f"share-{share}", count=24, seed=3, shard_size=24,
                            world_settings=pod_settings(4), progress=False, sight_share=share)  # fmt: skip
        points = dolphins_in_camera(out)
        occluded = np.array([hidden(sample)[0] for sample in points])
        angles = np.array([off_axis_deg(sample) for sample in points])
        shares[share] = occluded.mean(), (angles[:, 1:].min(axis=1) < angles[:, 0]).mean()
    assert shares[1.0][0] >= 0.8 and shares[0.0][0] < shares[1.0][0]  # the share puts one on the line of sight
    assert shares[0.0][1] > 0.1  # free companions often nearer the image centre than the target


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--dolphin-pod-size", "7"], "--dolphin-pod-size must be 1 to 6, got 7"),
        (["--dolphin-pod-size", "4", "--dolphin-pod-crossing"], "--dolphin-pod-crossing is for episodes"),
        (["--dolphin-pod-size", "4", "--sight-share", "1.5"], "--sight-share is a share of samples, 0 to 1"),
    ],
)
def test_a_bad_pod_is_refused_naming_the_flag_before_anything_is_written(tmp_path, capsys, flags, message):
    assert main(["dataset", "--out", str(tmp_path / "pod"), "--count", "2", *flags]) == 2
    assert f"dataset refused its settings: {message}" in capsys.readouterr().err  # one line, not a traceback
    assert not (tmp_path / "pod").exists()


@pytest.mark.parametrize(
    ("flag", "limit", "ranges_key", "column", "full_range", "unchanged"),
    [
        ("--max-azimuth-deg", 5.0, "azimuth_deg", 1, ALPHA_DEG, [0, 3]),  # near the image centre: d, elevation kept
        ("--max-elevation-deg", 3.0, "elevation_deg", 3, BETA_DEG, [1]),  # near the camera's level: theta kept
    ],
)
def test_a_narrower_range_draws_the_same_samples_scaled_into_it(
    tmp_path, flag, limit, ranges_key, column, full_range, unchanged
):
    common = ["--count", "24", "--seed", "3", "--vertical"]
    assert main(["dataset", "--out", str(tmp_path / "full"), *common]) == 0
    assert main(["dataset", "--out", str(tmp_path / "narrow"), *common, flag, str(limit)]) == 0
    full_meta, full = load(tmp_path / "full")
    meta, narrow = load(tmp_path / "narrow")
    assert full_meta["ranges"][ranges_key] == pytest.approx(full_range) and meta["ranges"][ranges_key] == limit
    drawn = narrow["labels"][:, column]
    assert np.abs(drawn).max() <= limit + 0.05 and np.abs(full["labels"][:, column]).max() > limit
    # The same draws otherwise: each sample's angle is the full range's scaled to the narrower one.
    assert np.allclose(drawn, full["labels"][:, column] * limit / full_range, atol=0.05)
    assert np.allclose(narrow["labels"][:, unchanged], full["labels"][:, unchanged], atol=0.05)


AZIMUTH_REFUSED = "--max-azimuth-deg must be above 0 and at most"
ELEVATION_REFUSED = "--max-elevation-deg must be above 0 and at most"


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--max-azimuth-deg", "0"], AZIMUTH_REFUSED),
        (["--max-azimuth-deg", "-3"], AZIMUTH_REFUSED),
        (["--max-azimuth-deg", "50"], AZIMUTH_REFUSED),
        (["--vertical", "--max-elevation-deg", "0"], ELEVATION_REFUSED),
        (["--vertical", "--max-elevation-deg", "40"], ELEVATION_REFUSED),
        (["--max-elevation-deg", "3"], "--max-elevation-deg draws a vertical dataset's elevations: add --vertical"),
    ],
)
def test_an_angle_range_outside_the_field_of_view_is_refused_by_name(tmp_path, capsys, flags, message):
    assert main(["dataset", "--out", str(tmp_path / "bad"), "--count", "2", *flags]) == 2
    assert f"dataset refused its settings: {message}" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
