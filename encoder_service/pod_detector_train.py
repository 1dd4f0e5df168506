"""`swimm train-detector`: fit the pod detector (encoder_service.pod_detector) on pod datasets (and lone dolphins').

    swimm dataset --out data/pod4 --count 40000 --seed 3 --workers 2 --masks --dolphin-pod-size 4
    swimm train-detector --dataset data/pod4 --out runs/pod_detector.pt

Every dolphin's label comes from the stored poses (encoder_service.pod_detector); frames are mirrored at random
(the pod's geometry is left-right symmetric). Validation is a fixed tail of each dataset: the share of seen targets
found (a peak within 2 pixels of the target's centre) and those detections' azimuth and distance errors.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from encoder_service.augment import AugmentSettings, check_share, contrast
from encoder_service.model import images_to_tensor
from encoder_service.pod_detector import (
    PodDetector,
    decode,
    detector_loss,
    dolphin_points,
    heatmap_targets,
    seen_dolphins,
    to_pixels,
)
from encoder_service.pod_encoder import load_detector, read_detector, save_detector
from services.geometry import CAMERA_AHEAD_M
from services.results import provenance, write_result

log = logging.getLogger(__name__)

THRESHOLD = 0.3  # a peak's least score to count as a dolphin


def pod_dataset_meta(folder: Path) -> dict:
    """A pod dataset's meta.json, or an error naming the folder and what it lacks."""
    path = folder / "meta.json"
    if not path.is_file():
        raise FileNotFoundError(f"--dataset {folder}: no meta.json (write one with `swimm dataset`)")
    meta = json.loads(path.read_text())
    if not meta.get("masks"):
        raise ValueError(f"--dataset {folder}: the detector needs a dataset with masks "
                         "(`swimm dataset --masks`, with --dolphin-pod-size N for a pod)")  # fmt: skip
    return meta


def load_pod_dataset(folder: Path) -> dict[str, np.ndarray]:
    """Images, poses, companions (none for a lone dolphin's dataset), every dolphin's pixels and the target's
    pixel count of every shard of a dataset with masks."""
    meta = pod_dataset_meta(folder)
    parts: dict[str, list[np.ndarray]] = {"images": [], "poses": [], "companions": [], "masks": [], "target_pixels": []}
    for shard in meta["shards"]:
        stem = folder / shard
        parts["images"].append(np.load(f"{stem}.images.npy"))
        parts["poses"].append(np.load(f"{stem}.poses.npy"))
        alone = np.zeros((len(parts["poses"][-1]), 0, 6), np.float32)
        parts["companions"].append(np.load(f"{stem}.companions.npy") if meta.get("pod") else alone)
        target = np.load(f"{stem}.masks.npy")
        parts["target_pixels"].append(target.sum(axis=(1, 2)))
        others = Path(f"{stem}.others.npy")  # a pod's companions' pixels
        parts["masks"].append(target | np.load(others) if others.is_file() else target)
    data = {name: np.concatenate(arrays) for name, arrays in parts.items()}
    points = dolphin_points(data["poses"].astype(np.float64), data["companions"].astype(np.float64))
    data["seen"], data["ignored"] = seen_dolphins(points, data["target_pixels"])
    data["pixels"] = to_pixels(points, data["images"].shape[1])
    data["azimuths"] = np.degrees(np.arctan2(points[..., 1], points[..., 0] + CAMERA_AHEAD_M))  # the task's
    positions = np.concatenate([data["poses"][:, None, 6:8], data["companions"][..., :2]], axis=1)
    data["distances"] = np.hypot(*(positions - data["poses"][:, None, :2]).transpose(2, 0, 1))
    return data


#: How a dolphin that a smaller pod's frames lack is filled in when datasets join: never seen, nowhere.
MISSING_DOLPHIN = {"seen": False, "ignored": False, "pixels": 0.0, "azimuths": 0.0, "distances": 1.0, "companions": 0.0}


def join_datasets(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Several datasets as one; pods of fewer dolphins (a lone dolphin's too) padded with dolphins never seen."""
    widest = max(part["seen"].shape[1] for part in parts)
    padded = []
    for part in parts:
        extra = widest - part["seen"].shape[1]
        padded.append(part | {name: _pad_dolphins(part[name], extra, fill) for name, fill in MISSING_DOLPHIN.items()})
    return {name: np.concatenate([part[name] for part in padded]) for name in padded[0]}


def _pad_dolphins(values: np.ndarray, extra: int, fill: float | bool) -> np.ndarray:
    """``values`` (frames, dolphins, ...) with ``extra`` more dolphins of ``fill``."""
    return np.pad(values, [(0, 0), (0, extra)] + [(0, 0)] * (values.ndim - 2), constant_values=fill)


def split_rows(counts: list[int], val_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Training and validation rows of datasets of ``counts`` frames joined in order: the last ``val_frames``
    frames held out, shared evenly among the datasets (each one's tail), so every kind of frame is validated."""
    shares = [val_frames // len(counts) + (index < val_frames % len(counts)) for index in range(len(counts))]
    train, val, start = [], [], 0
    for count, share in zip(counts, shares, strict=True):
        if share >= count:
            raise ValueError(f"--val-frames {val_frames}: a dataset of {count} frames cannot hold out {share}")
        train.append(np.arange(start, start + count - share))
        val.append(np.arange(start + count - share, start + count))
        start += count
    return np.concatenate(train), np.concatenate(val)


def batch(
    data: dict[str, np.ndarray],
    rows: np.ndarray,
    stride: int,
    mirror: np.ndarray | None = None,
    photometric: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple:
    """A batch's frames (N, 3, H, W) floats and its heatmap targets as tensors; ``mirror`` flips chosen rows, and
    ``photometric`` (frames, every dolphin's pixels -> frames) changes their look, never where the dolphins are."""
    images = data["images"][rows].copy()
    if photometric is not None:
        images = photometric(images, data["masks"][rows])
    pixels = data["pixels"][rows].copy()
    size = images.shape[1]
    if mirror is not None:
        images[mirror] = images[mirror][:, :, ::-1]
        pixels[mirror, :, 0] = size - pixels[mirror, :, 0]
    targets = heatmap_targets(pixels, data["distances"][rows], data["seen"][rows], data["ignored"][rows], size, stride)
    return images_to_tensor(images), {name: torch.from_numpy(value) for name, value in targets.items()}


def validate(model: PodDetector, data: dict[str, np.ndarray], rows: np.ndarray, threshold: float) -> dict[str, float]:
    """Recall of seen targets and the found ones' azimuth (deg) and distance (m) errors, plus false peaks a frame."""
    model.eval()
    found, theta_errors, d_errors, extra = 0, [], [], []
    size = data["images"].shape[1]
    with torch.no_grad():
        for start in range(0, len(rows), 256):
            chunk = rows[start : start + 256]
            frames, _ = batch(data, chunk, model.stride)
            detections = decode(*model(frames), threshold=threshold, size=size, stride=model.stride)
            for row, frame in zip(chunk, detections, strict=True):
                seen = np.nonzero(data["seen"][row])[0]
                extra.append(max(len(frame) - len(seen), 0))
                if not data["seen"][row, 0] or len(frame) == 0:
                    continue
                azimuth_true = data["azimuths"][row, 0]
                nearest = int(np.argmin(np.abs(frame.azimuth - azimuth_true)))
                if abs(frame.azimuth[nearest] - azimuth_true) < 2.5:
                    found += 1
                    theta_errors.append(abs(frame.azimuth[nearest] - azimuth_true))
                    d_errors.append(abs(frame.distance[nearest] - data["distances"][row, 0]))
    seen_targets = int(data["seen"][rows, 0].sum())
    model.train()
    return {
        "target_recall": found / max(seen_targets, 1),
        "theta_mae_deg": float(np.mean(theta_errors)) if theta_errors else float("nan"),
        "d_mae_m": float(np.mean(d_errors)) if d_errors else float("nan"),
        "extra_peaks_per_frame": float(np.mean(extra)),
    }


@dataclass
class TrainDetectorSettings(AugmentSettings):
    dataset: list[str] = field(default_factory=list)  # datasets with masks (`swimm dataset --masks`, a pod's with
    # --dolphin-pod-size N); several are read as one
    out: str = "runs/pod_detector.pt"  # the checkpoint, written after every epoch
    overwrite: bool = False  # replace an existing --out
    epochs: int = 10
    batch_size: int = 128
    lr: float = 2e-3  # the one-cycle schedule's peak
    val_frames: int = 2000  # frames held out to validate each epoch: each dataset's last, shared evenly
    seed: int = 0
    width: int = 16  # channels of the finest features; the coarser have 2x and 4x
    stride: int = 2  # pixels per heatmap cell: 2 or 4
    threshold: float = THRESHOLD  # a peak's least score to count as a dolphin, saved in the checkpoint
    init: str = ""  # a detector checkpoint to start from (its width and stride); default: fresh weights
    # share of training frames whose dolphins stand out from their water more or less than rendered, their size
    # unchanged (encoder_service.augment.contrast): distance read off size, not off how faded it is
    augment_contrast: float = 0.0


def check(settings: TrainDetectorSettings) -> None:
    """Refuse bad settings before any frame is read, naming the flag."""
    if not settings.dataset:
        raise ValueError(
            "--dataset: give at least one pod dataset folder (`swimm dataset --dolphin-pod-size N --masks`)"
        )
    for folder in settings.dataset:
        pod_dataset_meta(Path(folder))
    if settings.stride not in (2, 4):
        raise ValueError(f"--stride {settings.stride}: the detector reads 2 or 4 pixels a heatmap cell")
    settings.check_shares()
    check_share("--augment-contrast", settings.augment_contrast)
    if not 0.0 < settings.threshold < 1.0:
        raise ValueError(f"--threshold {settings.threshold}: a peak's score lies in (0, 1)")
    for flag, value in (("--epochs", settings.epochs), ("--batch-size", settings.batch_size),
                        ("--val-frames", settings.val_frames), ("--width", settings.width)):  # fmt: skip
        if value < 1:
            raise ValueError(f"{flag} {value}: must be at least 1")
    if settings.init:
        saved = read_detector(settings.init, "--init")
        for flag, mine, theirs in (("--width", settings.width, saved["width"]), ("--stride", settings.stride,
                                                                                   saved["stride"])):  # fmt: skip
            if mine != theirs:
                raise ValueError(f"{flag} {mine} differs from --init {settings.init}'s {theirs}")
    if Path(settings.out).exists() and not settings.overwrite:
        raise FileExistsError(f"--out {settings.out} exists: give --overwrite to replace it, or another --out")


def run(settings: TrainDetectorSettings) -> int:
    check(settings)
    torch.manual_seed(settings.seed)
    parts = [load_pod_dataset(Path(folder)) for folder in settings.dataset]
    data = join_datasets(parts)
    train_rows, val_rows = split_rows([len(part["images"]) for part in parts], settings.val_frames)
    model = load_detector(settings.init)[0].train() if settings.init else PodDetector(settings.width, settings.stride)
    optimiser = torch.optim.AdamW(model.parameters(), lr=settings.lr, weight_decay=1e-4)
    batches = len(train_rows) // settings.batch_size
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, max_lr=settings.lr, total_steps=settings.epochs * batches)
    rng = np.random.default_rng(settings.seed)

    def photometric(images: np.ndarray, masks: np.ndarray) -> np.ndarray:  # the frames themselves when all are off
        return settings.augmented(contrast(images, masks, rng, settings.augment_contrast), rng)

    history: list[dict[str, float]] = []
    out = Path(settings.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for epoch in range(1, settings.epochs + 1):
        order = rng.permutation(train_rows)
        started = time.time()
        bar = tqdm(range(batches), desc=f"epoch {epoch}/{settings.epochs}", mininterval=5)
        for step in bar:
            rows = order[step * settings.batch_size : (step + 1) * settings.batch_size]
            frames, targets = batch(data, rows, model.stride, mirror=rng.random(len(rows)) < 0.5,
                                    photometric=photometric)  # fmt: skip
            loss, parts_of_loss = detector_loss(*model(frames), targets)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
            bar.set_postfix({name: f"{value:.3f}" for name, value in parts_of_loss.items()})
        scores = validate(model, data, val_rows, settings.threshold)
        history.append(scores | {"epoch": epoch, "seconds": round(time.time() - started, 1)})
        log.info("epoch %d: %s", epoch, ", ".join(f"{k} {v:.3f}" for k, v in scores.items()))
        save_detector(model, out, settings.threshold, history)
    write_result(out.with_suffix(".json"), {"settings": asdict(settings), "history": history},
                 provenance(seeds=[settings.seed], datasets=settings.dataset))  # fmt: skip
    log.info("pod detector written to %s (fly it: swimm eval --backend inprocess --algo scripted-camera "
             "--encoder-checkpoint %s --dolphin-pod-size 4)", out, out)  # fmt: skip
    return 0
