"""`swimm dataset`: labelled frames for training the CMVAE, streamed to disk in shards.

On-disk format (version 1), a directory::

    meta.json                  {"format": "swimm-cmvae-dataset", "version": 1, "count", "seed",
                                "image_shape", "shard_size", "label_names", "pose_names", "shards",
                                "paired", "ranges", "world", "masks"}
    shard-00000.images.npy     uint8   (n, 64, 64, 3) RGB
    shard-00000.labels.npy     float32 (n, 3): d (m), theta (signed azimuth, deg, + = left), psi (deg); with
                               ``vertical`` (n, 4): elevation (deg, + = above the camera's level) added
    shard-00000.poses.npy      float32 (n, 12): see POSE_NAMES
    shard-00000.clean.npy      uint8   (n, 64, 64, 3): paired datasets only (``"paired": true``), the same
                               frames before image noise, the target a denoising encoder reconstructs
    shard-00000.masks.npy      bool    (n, 64, 64): datasets written with ``masks`` (``"masks": true``), which
                               pixels show the dolphin (MuJoCo's segmentation render of the same pose); in a pod,
                               which show the target (a companion in front of it takes its pixels)
    shard-00000.others.npy     bool    (n, 64, 64): pod datasets with masks, which pixels show any companion
    shard-00000.companions.npy float32 (n, size - 1, 6): pod datasets, each companion's x, y, z, roll, pitch, yaw
                               (the target's pose columns, see POSE_NAMES)
    ...

Each shard is written through a memory map as it is filled and meta.json
last, so 3e5 images never sit in memory and a half-written directory is
recognisable (no meta.json). Readers ``np.load(..., mmap_mode="r")`` shards.

Sampling follows the SPEC's generation ranges (the paper's Table 6): rover
anywhere in +-30 m with a depth band, any heading; target 2-10 m away within
the camera's half field of view, any yaw, any turn weight and tail phase. A
``vertical`` dataset (the 3d task's frames) puts the target anywhere in the
vertical field of view too, within the dolphin's depth band.
Sample ``i`` is drawn from its own generator seeded by (seed, i), so a
dataset is reproducible and any sample can be regenerated alone.

A pod dataset (``--dolphin-pod-size`` > 1, ``"pod"`` in meta.json) places the target's companions round it as at
any moment of an episode (sim_service/pod.py), from a child of the sample's generator, so its labels and poses
are the single-dolphin dataset's of the same seed; ``sight_share`` of the samples put one halfway along the line
of sight, hiding part of the target. Labels stay the target's.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from services.geometry import (
    ALPHA_DEG,
    BETA_DEG,
    CAMERA_ABOVE_M,
    CAMERA_AHEAD_M,
    LABEL_NAMES,
    VERTICAL_LABEL_NAMES,
    quat_to_euler,
    relative_geometry,
    vertical_geometry,
)
from services.results import refuse_held_folder
from services.settings import PosInt
from sim_service.settings import WorldSettings
from sim_service.world import World

log = logging.getLogger(__name__)

FORMAT = "swimm-cmvae-dataset"
VERSION = 1
POSE_NAMES = (
    "rover_x", "rover_y", "rover_z", "rover_roll", "rover_pitch", "rover_yaw",
    "target_x", "target_y", "target_z", "target_roll", "target_pitch", "target_yaw",
)  # fmt: skip


@dataclass(frozen=True)
class SamplingRanges:
    """Generation ranges (SPEC, the paper's Table 6). Depth band: 4 m +- 3.5 m keeps the camera underwater."""

    rover_xy: float = 30.0
    rover_depth: tuple[float, float] = (0.5, 7.5)
    distance: tuple[float, float] = (2.0, 10.0)
    azimuth_deg: float = ALPHA_DEG
    target_depth_offset: float = 0.5  # the target swims within +-0.5 m of the rover's depth
    turn_weight: float = 1.3
    #: Vertical datasets: the target's elevation, U[-max, max] degrees (the camera's vertical half field of view),
    #: its depth kept within the band (the 3d dolphin's) by choosing the rover's depth; 0 = planar.
    elevation_deg: float = 0.0
    target_depth: tuple[float, float] = (0.3, 8.0)

    @property
    def vertical(self) -> bool:
        return self.elevation_deg > 0.0

    @property
    def label_names(self) -> tuple[str, ...]:
        return VERTICAL_LABEL_NAMES if self.vertical else LABEL_NAMES


#: What ``swimm dataset --vertical`` samples.
VERTICAL_RANGES = SamplingRanges(elevation_deg=BETA_DEG)


@dataclass
class DatasetSettings:
    out: str = "data/cmvae-train"
    count: PosInt = 1000
    seed: int = 3  # the paper: train seed 3, test seed 5
    shard_size: PosInt = 4096
    workers: PosInt = 1  # processes rendering shards in parallel; the bytes do not depend on it
    paired: bool = False  # also keep each noisy frame's clean render (needs noise on, e.g. --noise-preset harsh)
    masks: bool = False  # also write which pixels show the dolphin, for the encoder's mask head (train --mask-weight)
    vertical: bool = False  # the target anywhere in the vertical field of view too, labelled with its elevation
    sight_share: float = 0.25  # pod datasets (--dolphin-pod-size > 1): samples with a companion hiding the target
    #: The target's azimuth U[-max, max] degrees; below the camera's half field of view for frames near the image
    #: centre, where a closed loop holds the dolphin and the azimuth read must be finest.
    max_azimuth_deg: float = ALPHA_DEG
    #: Vertical datasets: the target's elevation U[-max, max] degrees; below the camera's vertical half field of
    #: view for frames near the camera's level, where the planar task's dolphin swims.
    max_elevation_deg: float = BETA_DEG
    world: WorldSettings = field(default_factory=WorldSettings, metadata={"flatten": True})


def sample_pose(world: World, rng: np.random.Generator, ranges: SamplingRanges, sight_share: float = 0.0):
    """Place rover and dolphin (and a pod's companions, ``sight_share`` of the time one on the line of sight) at
    one random pose and return (telemetry, image)."""
    rover = np.array(
        [*rng.uniform(-ranges.rover_xy, ranges.rover_xy, 2), -rng.uniform(*ranges.rover_depth)], dtype=float
    )
    rover_yaw = rng.uniform(-math.pi, math.pi)
    distance = rng.uniform(*ranges.distance)
    bearing = rover_yaw + math.radians(rng.uniform(-ranges.azimuth_deg, ranges.azimuth_deg))
    depth_offset = rng.uniform(-ranges.target_depth_offset, ranges.target_depth_offset)
    target = rover + np.array([distance * math.cos(bearing), distance * math.sin(bearing), depth_offset])
    target_yaw = rng.uniform(-math.pi, math.pi)
    turn_weight = rng.uniform(-ranges.turn_weight, ranges.turn_weight)
    phase = rng.uniform(0.0, 1.0)
    if ranges.vertical:  # drawn after the planar draws, so a planar dataset's samples stay what they were
        camera = rover[:2] + CAMERA_AHEAD_M * np.array([math.cos(rover_yaw), math.sin(rover_yaw)])
        elevation = math.radians(rng.uniform(-ranges.elevation_deg, ranges.elevation_deg))
        rise = CAMERA_ABOVE_M + math.dist(target[:2], camera) * math.tan(elevation)  # above the rover's centre
        rover[2] = -_rover_depth_for(rise, rng, ranges)
        target[2] = rover[2] + rise
    return world.place(rover, rover_yaw, target, target_yaw, turn_weight, phase, noise_rng=rng, sight_share=sight_share)


def _rover_depth_for(depth_offset: float, rng: np.random.Generator, ranges: SamplingRanges) -> float:
    """A rover depth within its range that puts a target ``depth_offset`` m above it inside the target's band."""
    low = max(ranges.rover_depth[0], ranges.target_depth[0] + depth_offset)
    high = min(ranges.rover_depth[1], ranges.target_depth[1] + depth_offset)
    return rng.uniform(low, high)


def labels_and_pose(telemetry, vertical: bool = False) -> tuple[np.ndarray, np.ndarray]:
    geometry = relative_geometry(telemetry)
    elevation = [vertical_geometry(telemetry).elevation] if vertical else []
    labels = np.array([geometry.d, geometry.azimuth, geometry.psi, *elevation], dtype=np.float32)
    rover_euler = np.degrees(quat_to_euler(telemetry.rover_quat))
    target_euler = np.degrees(quat_to_euler(telemetry.target_quat))
    pose = np.concatenate([telemetry.rover_pos, rover_euler, telemetry.target_pos, target_euler]).astype(np.float32)
    return labels, pose


def _companion_poses(world: World) -> np.ndarray:
    """Each companion's pose as the target's is written: position, then roll, pitch and yaw in degrees."""
    positions, quats = world.companion_bodies()
    eulers = np.degrees([quat_to_euler(quat) for quat in quats])
    return np.concatenate([positions, eulers], axis=1)


def _write_shard(
    out: Path,
    index: int,
    start: int,
    n: int,
    seed: int,
    paired: bool,
    masks: bool,
    sight_share: float,
    world: World,
    ranges: SamplingRanges,
    bar: tqdm | None,
) -> str:
    """Render samples start..start+n into shard files named by ``index``; returns the shard's name."""
    size = world.settings.image_size
    name = f"shard-{index:05d}"
    images = np.lib.format.open_memmap(out / f"{name}.images.npy", "w+", np.uint8, (n, size, size, 3))
    labels = np.lib.format.open_memmap(out / f"{name}.labels.npy", "w+", np.float32, (n, len(ranges.label_names)))
    poses = np.lib.format.open_memmap(out / f"{name}.poses.npy", "w+", np.float32, (n, 12))
    arrays = [images, labels, poses]
    if paired:
        clean = np.lib.format.open_memmap(out / f"{name}.clean.npy", "w+", np.uint8, (n, size, size, 3))
        arrays.append(clean)
    if masks:
        target_masks = np.lib.format.open_memmap(out / f"{name}.masks.npy", "w+", np.bool_, (n, size, size))
        arrays.append(target_masks)
    companions = world.pod.size - 1
    if companions:
        companion_poses = np.lib.format.open_memmap(
            out / f"{name}.companions.npy", "w+", np.float32, (n, companions, 6)
        )
        arrays.append(companion_poses)
    others = masks and companions > 0
    if others:
        other_masks = np.lib.format.open_memmap(out / f"{name}.others.npy", "w+", np.bool_, (n, size, size))
        arrays.append(other_masks)
    for j in range(n):
        telemetry, image = sample_pose(world, np.random.default_rng([seed, start + j]), ranges, sight_share)
        images[j] = image
        if paired:
            clean[j] = world.clean_frame
        if others:
            target_masks[j], other_masks[j] = world.dolphin_masks()
        elif masks:
            target_masks[j] = world.target_mask()  # the pose just placed; noise never moves pixels
        labels[j], poses[j] = labels_and_pose(telemetry, ranges.vertical)
        if companions:
            companion_poses[j] = _companion_poses(world)
        if bar is not None:
            bar.update(1)
    for array in arrays:
        array.flush()
    return name


def _shard_in_worker(job: tuple) -> tuple[str, int]:
    """Process-pool entry point: each worker process builds its own World (and GL context) once."""
    out, index, start, n, seed, paired, masks, sight_share, settings, ranges = job
    global _worker_world
    if _worker_world is None:
        _worker_world = World(settings)
    return _write_shard(out, index, start, n, seed, paired, masks, sight_share, _worker_world, ranges, None), n


_worker_world: World | None = None


def write_dataset(
    out_dir: str | Path,
    count: int,
    seed: int,
    shard_size: int = 4096,
    world_settings: WorldSettings | None = None,
    ranges: SamplingRanges | None = None,
    progress: bool = True,
    workers: int = 1,
    paired: bool = False,
    masks: bool = False,
    sight_share: float = DatasetSettings.sight_share,
) -> Path:
    """Render ``count`` labelled frames into ``out_dir`` (see the module docstring); returns the directory.

    With ``workers > 1`` shards are rendered by that many processes; per-sample seeds make the
    bytes identical to a single-process run. ``paired`` keeps each frame's clean render too, ``masks`` the
    dolphin's pixels (and a pod's companions'). A pod (``world_settings.dolphin.pod_size`` > 1) puts a companion
    on the line of sight in ``sight_share`` of the samples.
    """
    if count <= 0 or shard_size <= 0 or workers <= 0:
        raise ValueError(f"count, shard_size and workers must be positive (got {count}, {shard_size}, {workers})")
    settings = world_settings or WorldSettings()
    check_request(out_dir, settings, paired, sight_share)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ranges = ranges or SamplingRanges()
    jobs = [
        (out, index, start, min(shard_size, count - start), seed, paired, masks, sight_share, settings, ranges)
        for index, start in enumerate(range(0, count, shard_size))
    ]
    with tqdm(total=count, desc=f"dataset {out.name}", unit="img", disable=not progress) as bar:
        if workers == 1:
            world = World(settings)
            try:
                shards = [_write_shard(*job[:8], world, ranges, bar) for job in jobs]
            finally:
                world.close()
        else:
            with multiprocessing.get_context("spawn").Pool(workers) as pool:
                shards = []
                for name, n in pool.imap(_shard_in_worker, jobs):
                    shards.append(name)
                    bar.update(n)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "count": count,
        "seed": seed,
        "image_shape": [settings.image_size, settings.image_size, 3],
        "shard_size": shard_size,
        "label_names": list(ranges.label_names),
        "pose_names": list(POSE_NAMES),
        "shards": shards,
        "paired": paired,
        "ranges": asdict(ranges),
        "world": asdict(settings),
    }
    if masks:  # recorded only when on, so a dataset without masks is byte for byte what it was before the flag
        meta["masks"] = True
    if settings.dolphin.pod_size > 1:  # likewise: a lone dolphin's meta.json is what it was before pods
        meta["pod"] = {"size": settings.dolphin.pod_size, "sight_share": sight_share, "others": masks}
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    log.info("wrote %d images in %d shards to %s", count, len(shards), out)
    return out


def check_request(out_dir: str | Path, settings: WorldSettings, paired: bool, sight_share: float) -> None:
    """Refuse a dataset that cannot be written as asked (its world, a pod, pairs, a folder holding one), before
    any frame is rendered."""
    settings.check()
    _check_pod(settings, sight_share)
    if paired and not settings.noise.resolved().enabled:
        raise ValueError("a paired dataset pairs noisy frames with clean ones: switch noise on (--noise-preset harsh)")
    refuse_held_folder("--out", out_dir, ["meta.json"], "a dataset", "choose another --out or delete it")


def check(settings: DatasetSettings) -> None:
    """`swimm dataset`'s check."""
    sampling_ranges(settings)
    check_request(settings.out, settings.world, settings.paired, settings.sight_share)


def run(settings: DatasetSettings) -> int:
    write_dataset(
        settings.out, settings.count, settings.seed, settings.shard_size, settings.world,
        ranges=sampling_ranges(settings), workers=settings.workers, paired=settings.paired,
        masks=settings.masks, sight_share=settings.sight_share,
    )  # fmt: skip
    return 0


def sampling_ranges(settings: DatasetSettings) -> SamplingRanges:
    """What a `swimm dataset` run draws: the planar or the vertical ranges, the azimuth (and a vertical dataset's
    elevation) within its maximum."""
    if not 0.0 < settings.max_azimuth_deg <= ALPHA_DEG:
        raise ValueError(f"--max-azimuth-deg must be above 0 and at most the camera's half field of view "
                         f"{ALPHA_DEG:g}: got {settings.max_azimuth_deg:g}")  # fmt: skip
    if not 0.0 < settings.max_elevation_deg <= BETA_DEG:
        raise ValueError(f"--max-elevation-deg must be above 0 and at most the camera's vertical half field of view "
                         f"{BETA_DEG:g}: got {settings.max_elevation_deg:g}")  # fmt: skip
    if settings.max_elevation_deg != BETA_DEG and not settings.vertical:
        raise ValueError("--max-elevation-deg draws a vertical dataset's elevations: add --vertical")
    if not settings.vertical:
        return replace(SamplingRanges(), azimuth_deg=settings.max_azimuth_deg)
    return replace(VERTICAL_RANGES, azimuth_deg=settings.max_azimuth_deg, elevation_deg=settings.max_elevation_deg)


def _check_pod(settings: WorldSettings, sight_share: float) -> None:
    """Refuse a bad pod before any file is written, naming the flags: a dataset draws its own crossings."""
    settings.dolphin.check()
    if settings.dolphin.pod_crossing:
        raise ValueError("--dolphin-pod-crossing is for episodes: a pod dataset puts companions on the line of sight "
                         "by itself (--sight-share)")  # fmt: skip
    if not 0.0 <= sight_share <= 1.0:
        raise ValueError(f"--sight-share is a share of samples, 0 to 1: got {sight_share}")
