"""Reading a CMVAE dataset from disk (the format `swimm dataset` writes; see notes/interfaces).

The full training set is 2.7e5 frames (3.3 GB), so shards are memory-mapped
and only the rows of the current batch are read. Splits and shuffles are pure
functions of a seed (and the epoch), so a resumed run sees the same order.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from encoder_service.model import IMAGE_SHAPE, LABEL_SETS
from services.identity import TARGET, followed_dolphin, level_camera_points

log = logging.getLogger(__name__)

DATASET_FORMAT = "swimm-cmvae-dataset"
DATASET_VERSION = 1
T = TypeVar("T")


class DatasetFormatError(ValueError):
    """The folder is not a dataset this code can read; the message names the problem."""


@dataclass(frozen=True)
class Batch:
    images: np.ndarray  # uint8 (B, 64, 64, 3) RGB
    labels: np.ndarray  # float32 (B, labels): d m, theta deg (signed azimuth), psi deg[, elevation deg]
    indices: np.ndarray  # int64 (B,): dataset rows, to pair a frame with its twin in another dataset
    clean: np.ndarray | None = None  # uint8 (B, 64, 64, 3): paired datasets' frames before noise, else None
    masks: np.ndarray | None = None  # bool (B, 64, 64): the dolphin's pixels, datasets written with --masks, else None
    #: bool (B,): whether the target is the dolphin nearest the image centre, the one tracking engages on (always,
    #: for a lone dolphin); None: not known, read as always
    centred: np.ndarray | None = None


class CMVAEDataset:
    """A validated dataset folder with its shards memory-mapped; rows are read on demand."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.meta = _read_meta(self.root)
        self._images: list[np.ndarray] = []
        self._labels: list[np.ndarray] = []
        self._clean: list[np.ndarray] = []
        self._masks: list[np.ndarray] = []
        self._dolphins: list[tuple[np.ndarray, np.ndarray]] = []  # pods: each shard's (poses, companions)
        for shard in self.meta["shards"]:
            images, labels = _open_shard(self.root, shard, len(self.label_names))
            self._images.append(images)
            self._labels.append(labels)
            if self.paired:
                self._clean.append(_open_clean(self.root, shard, len(images)))
            if self.has_masks:
                self._masks.append(_open_masks(self.root, shard, len(images)))
            if self.pod_size > 1:
                self._dolphins.append(_open_dolphins(self.root, shard, len(images), self.pod_size))
        sizes = [len(images) for images in self._images]
        if sum(sizes) != self.meta["count"]:
            raise DatasetFormatError(
                f"{self.root}: meta.json says count={self.meta['count']} but the shards hold {sum(sizes)} rows"
            )
        #: first global row of each shard, plus the end
        self._starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def seed(self) -> int:
        return int(self.meta["seed"])

    @property
    def label_names(self) -> tuple[str, ...]:
        """(d, theta, psi), or with elevation for a `swimm dataset --vertical` folder."""
        return tuple(self.meta["label_names"])

    @property
    def paired(self) -> bool:
        """True when each (noisy) frame has its clean render beside it (`swimm dataset --paired`)."""
        return bool(self.meta.get("paired", False))

    @property
    def has_masks(self) -> bool:
        """True when each frame has the dolphin's pixels beside it (`swimm dataset --masks`)."""
        return bool(self.meta.get("masks", False))

    @property
    def pod_size(self) -> int:
        """Dolphins in each frame, the target included (`swimm dataset --dolphin-pod-size`); 1 for a lone dolphin."""
        return int(self.meta.get("pod", {}).get("size", 1))

    def read_labels(self, indices: np.ndarray) -> np.ndarray:
        """Labels of rows ``indices`` only (no image reads), float32 (len, labels)."""
        indices = np.asarray(indices, dtype=np.int64)
        shard_of = np.searchsorted(self._starts, indices, side="right") - 1
        labels = np.empty((len(indices), len(self.label_names)), dtype=np.float32)
        for shard in np.unique(shard_of):
            chosen = shard_of == shard
            labels[chosen] = self._labels[shard][indices[chosen] - self._starts[shard]]
        return labels

    def read_poses(self, indices: np.ndarray) -> np.ndarray:
        """The rows' poses (N, 12; sim_service.dataset.POSE_NAMES: rover x, y, z, roll, pitch, yaw, then the
        target's, degrees), read from the shards' ``poses.npy``."""
        indices = np.asarray(indices, dtype=np.int64)
        poses = np.empty((len(indices), 12), dtype=np.float32)
        shard_of = np.searchsorted(self._starts, indices, side="right") - 1
        for shard in np.unique(shard_of):
            chosen = shard_of == shard
            path = self.root / f"{self.meta['shards'][shard]}.poses.npy"
            if not path.is_file():
                raise DatasetFormatError(f"{path} is missing: this dataset holds no poses")
            poses[chosen] = np.load(path, mmap_mode="r")[indices[chosen] - self._starts[shard]]
        return poses

    def read(self, indices: np.ndarray) -> Batch:
        """Rows ``indices`` (any order) as one in-memory batch, in that order.

        Rows are fetched shard by shard in ascending order, which turns a random
        batch into a few forward reads of the memory map.
        """
        indices = np.asarray(indices, dtype=np.int64)
        if indices.size and (indices.min() < 0 or indices.max() >= len(self)):
            raise IndexError(f"row indices must lie in [0, {len(self)}), got {indices.min()}..{indices.max()}")
        images = np.empty((len(indices), *IMAGE_SHAPE), dtype=np.uint8)
        labels = np.empty((len(indices), len(self.label_names)), dtype=np.float32)
        clean = np.empty_like(images) if self.paired else None
        masks = np.empty(images.shape[:3], dtype=bool) if self.has_masks else None
        centred = np.ones(len(indices), dtype=bool)  # a lone dolphin is always the one nearest the centre
        order = np.argsort(indices, kind="stable")
        shard_of = np.searchsorted(self._starts, indices[order], side="right") - 1
        for shard in np.unique(shard_of):
            positions = order[shard_of == shard]
            rows = indices[positions] - self._starts[shard]
            images[positions] = self._images[shard][rows]
            labels[positions] = self._labels[shard][rows]
            if clean is not None:
                clean[positions] = self._clean[shard][rows]
            if masks is not None:
                masks[positions] = self._masks[shard][rows]
            if self._dolphins:
                poses, companions = self._dolphins[shard]
                centred[positions] = centred_targets(poses[rows], companions[rows])
        return Batch(images=images, labels=labels, indices=indices, clean=clean, masks=masks, centred=centred)


class DatasetUnion:
    """Several dataset folders read as one: rows numbered folder after folder, each read from its own shards.

    Training on a mixture of conditions (say randomised noise and one fixed preset) needs no merged copy on disk.
    """

    def __init__(self, parts: list[CMVAEDataset]) -> None:
        if not parts:
            raise ValueError("a dataset union needs at least one folder")
        if len({part.label_names for part in parts}) > 1:
            labels = ", ".join(f"{part.root}: {list(part.label_names)}" for part in parts)
            raise DatasetFormatError(
                f"cannot mix datasets with different labels ({labels}); write all --vertical or none"
            )
        if len({part.paired for part in parts}) > 1:
            paired = [str(part.root) for part in parts if part.paired]
            raise DatasetFormatError(
                f"cannot mix paired and unpaired datasets (paired: {', '.join(paired)}); write all --paired or none"
            )
        self.parts = parts
        self.root = parts[0].root
        self.meta = parts[0].meta
        self._starts = np.concatenate([[0], np.cumsum([len(part) for part in parts])]).astype(np.int64)

    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def seed(self) -> int:
        return self.parts[0].seed

    @property
    def label_names(self) -> tuple[str, ...]:
        return self.parts[0].label_names

    @property
    def paired(self) -> bool:
        return self.parts[0].paired

    @property
    def has_masks(self) -> bool:
        """True when every folder has masks: a batch's masks are all there or all absent."""
        return all(part.has_masks for part in self.parts)

    def _by_part(self, indices: np.ndarray) -> Iterator[tuple[CMVAEDataset, np.ndarray, np.ndarray]]:
        """(part, positions in ``indices``, the part's own rows) for each part that ``indices`` touch."""
        indices = np.asarray(indices, dtype=np.int64)
        if indices.size and (indices.min() < 0 or indices.max() >= len(self)):
            raise IndexError(f"row indices must lie in [0, {len(self)}), got {indices.min()}..{indices.max()}")
        part_of = np.searchsorted(self._starts, indices, side="right") - 1
        for part in np.unique(part_of):
            positions = np.flatnonzero(part_of == part)
            yield self.parts[part], positions, indices[positions] - self._starts[part]

    def read_labels(self, indices: np.ndarray) -> np.ndarray:
        labels = np.empty((len(indices), len(self.label_names)), dtype=np.float32)
        for part, positions, rows in self._by_part(indices):
            labels[positions] = part.read_labels(rows)
        return labels

    def read_poses(self, indices: np.ndarray) -> np.ndarray:
        poses = np.empty((len(indices), 12), dtype=np.float32)
        for part, positions, rows in self._by_part(indices):
            poses[positions] = part.read_poses(rows)
        return poses

    def read(self, indices: np.ndarray) -> Batch:
        indices = np.asarray(indices, dtype=np.int64)
        images = np.empty((len(indices), *IMAGE_SHAPE), dtype=np.uint8)
        labels = np.empty((len(indices), len(self.label_names)), dtype=np.float32)
        clean = np.empty_like(images) if self.paired else None
        masks = np.empty(images.shape[:3], dtype=bool) if self.has_masks else None
        centred = np.empty(len(indices), dtype=bool)
        for part, positions, rows in self._by_part(indices):
            batch = part.read(rows)
            images[positions], labels[positions] = batch.images, batch.labels
            if clean is not None:
                clean[positions] = batch.clean
            if masks is not None:
                masks[positions] = batch.masks
            centred[positions] = batch.centred
        return Batch(images=images, labels=labels, indices=indices, clean=clean, masks=masks, centred=centred)


AnyDataset = CMVAEDataset | DatasetUnion


def require_masks(dataset: AnyDataset, wanted_by: str) -> None:
    """Refuse, naming each folder without masks and how to write them, when ``wanted_by`` (a flag) needs masks."""
    parts = dataset.parts if isinstance(dataset, DatasetUnion) else [dataset]
    missing = [str(part.root) for part in parts if not part.has_masks]
    if missing:
        raise DatasetFormatError(
            f"{wanted_by} needs the dolphin's masks, but {', '.join(missing)} holds none: "
            f"write the dataset again with `swimm dataset --masks`"
        )


def open_datasets(roots: str | list[str]) -> AnyDataset:
    """One dataset folder, or several read as one (`DatasetUnion`)."""
    roots = [roots] if isinstance(roots, str | Path) else list(roots)
    if len(roots) == 1:
        return CMVAEDataset(roots[0])
    return DatasetUnion([CMVAEDataset(root) for root in roots])


def _read_meta(root: Path) -> dict[str, Any]:
    path = root / "meta.json"
    if not path.is_file():
        raise DatasetFormatError(f"{root} is not a CMVAE dataset: {path} is missing (make one with `swimm dataset`)")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetFormatError(f"{path} is not valid JSON: {exc}") from None
    expected = {"format": DATASET_FORMAT, "version": DATASET_VERSION, "image_shape": list(IMAGE_SHAPE)}
    for key, value in expected.items():
        if meta.get(key) != value:
            raise DatasetFormatError(f"{path}: {key} is {meta.get(key)!r}, expected {value!r}")
    if not any(meta.get("label_names") == list(labels) for labels in LABEL_SETS):
        sets = " or ".join(str(list(labels)) for labels in LABEL_SETS)
        raise DatasetFormatError(f"{path}: label_names is {meta.get('label_names')!r}, expected {sets}")
    for key in ("count", "seed"):
        if not isinstance(meta.get(key), int):
            raise DatasetFormatError(f"{path}: {key} must be an integer, got {meta.get(key)!r}")
    if not isinstance(meta.get("shards"), list) or not meta["shards"]:
        raise DatasetFormatError(f"{path}: shards must be a non-empty list of shard names")
    return meta


def _open_shard(root: Path, shard: str, label_count: int) -> tuple[np.ndarray, np.ndarray]:
    arrays = []
    for part, dtype, shape in (("images", np.uint8, IMAGE_SHAPE), ("labels", np.float32, (label_count,))):
        path = root / f"{shard}.{part}.npy"
        if not path.is_file():
            raise DatasetFormatError(f"shard file {path} is missing")
        array = np.load(path, mmap_mode="r")
        if array.dtype != dtype or array.ndim != 1 + len(shape) or tuple(array.shape[1:]) != shape:
            raise DatasetFormatError(
                f"{path}: expected {np.dtype(dtype).name} (n, {', '.join(map(str, shape))}), "
                f"got {array.dtype} {array.shape}"
            )
        arrays.append(array)
    images, labels = arrays
    if len(images) != len(labels):
        raise DatasetFormatError(f"{root / shard}: {len(images)} images but {len(labels)} labels")
    return images, labels


def _open_clean(root: Path, shard: str, count: int) -> np.ndarray:
    path = root / f"{shard}.clean.npy"
    if not path.is_file():
        raise DatasetFormatError(f"meta.json says the dataset is paired, but shard file {path} is missing")
    clean = np.load(path, mmap_mode="r")
    if clean.dtype != np.uint8 or clean.shape != (count, *IMAGE_SHAPE):
        shape = ", ".join(map(str, IMAGE_SHAPE))
        raise DatasetFormatError(f"{path}: expected uint8 ({count}, {shape}), got {clean.dtype} {clean.shape}")
    return clean


def _open_masks(root: Path, shard: str, count: int) -> np.ndarray:
    path = root / f"{shard}.masks.npy"
    if not path.is_file():
        raise DatasetFormatError(f"meta.json says the dataset has masks, but shard file {path} is missing")
    masks = np.load(path, mmap_mode="r")
    if masks.dtype != np.bool_ or masks.shape != (count, *IMAGE_SHAPE[:2]):
        shape = ", ".join(map(str, IMAGE_SHAPE[:2]))
        raise DatasetFormatError(f"{path}: expected bool ({count}, {shape}), got {masks.dtype} {masks.shape}")
    return masks


def _open_dolphins(root: Path, shard: str, count: int, pod_size: int) -> tuple[np.ndarray, np.ndarray]:
    """A pod shard's poses (count, 12) and companions' poses (count, pod_size - 1, 6), memory-mapped."""
    arrays = []
    for part, shape in (("poses", (count, 12)), ("companions", (count, pod_size - 1, 6))):
        path = root / f"{shard}.{part}.npy"
        if not path.is_file():
            raise DatasetFormatError(f"meta.json says the dataset is a pod, but shard file {path} is missing")
        array = np.load(path, mmap_mode="r")
        if array.shape != shape:
            raise DatasetFormatError(f"{path}: expected shape {shape}, got {array.shape}")
        arrays.append(array)
    poses, companions = arrays
    return poses, companions


#: Datasets place the rover level (its roll and pitch 0 but for float error); the camera frame assumes it.
LEVEL_TOLERANCE_DEG = 0.01


def centred_targets(poses: np.ndarray, companions: np.ndarray) -> np.ndarray:
    """Whether each row's target is the dolphin the sim's rover would follow, the one in view, not hidden and
    nearest the image centre (services.identity): poses (N, 12) and companions (N, K, 6) as a pod dataset stores
    them. Such a target is the one tracking engages on when the camera is centred on it."""
    poses = np.asarray(poses, dtype=np.float64)
    if np.abs(poses[:, 3:5]).max(initial=0.0) > LEVEL_TOLERANCE_DEG:
        raise DatasetFormatError("a pod dataset's rover must be level (roll and pitch 0): the camera frame assumes it")
    positions = np.concatenate([poses[:, None, 6:9], np.asarray(companions, dtype=np.float64)[..., :3]], axis=1)
    points = level_camera_points(poses[:, :3], poses[:, 5], positions)
    return np.array([followed_dolphin(row) == TARGET for row in points], dtype=bool)


def split_indices(count: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic (train, validation) row indices, each sorted; validation gets round(count * fraction) rows."""
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must lie in [0, 1), got {val_fraction}")
    n_val = int(round(count * val_fraction))
    if val_fraction > 0 and not 0 < n_val < count:
        raise ValueError(f"cannot hold out {val_fraction:.0%} of {count} rows and keep both parts non-empty")
    permutation = np.random.default_rng(seed).permutation(count)
    return np.sort(permutation[n_val:]), np.sort(permutation[:n_val])


def iter_batches(
    dataset: AnyDataset,
    indices: np.ndarray,
    batch_size: int,
    shuffle_seed: int | tuple[int, ...] | None = None,
    max_batches: int = 0,
) -> Iterator[Batch]:
    """Batches over ``indices``; shuffled by ``shuffle_seed`` (e.g. (seed, epoch)) when given; the last may be short.

    ``max_batches`` > 0 stops early (quick runs); 0 means all.
    """
    if shuffle_seed is not None:
        indices = np.random.default_rng(shuffle_seed).permutation(indices)
    stops = range(0, len(indices), batch_size)
    if max_batches > 0:
        stops = stops[:max_batches]
    for start in stops:
        yield dataset.read(indices[start : start + batch_size])


def count_batches(n_rows: int, batch_size: int, max_batches: int = 0) -> int:
    full = -(-n_rows // batch_size)
    return min(full, max_batches) if max_batches > 0 else full


def prefetch(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """Produce ``items`` on a background thread, ``depth`` ahead, so disk reads overlap compute.

    NumPy copies from a memory map release the GIL, so one thread is enough to
    hide the read latency behind a training step. Errors in the producer are
    re-raised in the consumer.
    """
    buffer: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                if stop.is_set():
                    return
                buffer.put(("item", item))
            buffer.put(("end", None))
        except BaseException as exc:  # handed to the consumer, not lost on this thread
            buffer.put(("error", exc))

    worker = threading.Thread(target=produce, name="batch-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            kind, payload = buffer.get()
            if kind == "end":
                return
            if kind == "error":
                raise payload
            yield payload
    finally:
        stop.set()
        while worker.is_alive():  # unblock a producer waiting on a full queue
            try:
                buffer.get_nowait()
            except queue.Empty:
                worker.join(timeout=0.01)
