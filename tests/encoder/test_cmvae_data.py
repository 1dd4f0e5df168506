"""The dataset reader: format checks, row reads across shards, splits and shuffles by seed, prefetching."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from encoder_service.data import (
    CMVAEDataset,
    DatasetFormatError,
    DatasetUnion,
    count_batches,
    iter_batches,
    open_datasets,
    prefetch,
    split_indices,
)
from tests.encoder.cmvae_testdata import write_dataset


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("cmvae-data"), count=50, seed=4, shard_size=16)  # shards 16,16,16,2


def test_rows_read_across_shards_match_the_files_in_any_order(dataset_dir: Path) -> None:
    dataset = CMVAEDataset(dataset_dir)
    assert len(dataset) == 50 and dataset.seed == 4
    rows = np.array([49, 0, 17, 16, 33, 15, 32])
    batch = dataset.read(rows)
    assert batch.images.shape == (7, 64, 64, 3) and batch.images.dtype == np.uint8
    assert batch.labels.shape == (7, 3) and batch.labels.dtype == np.float32
    for position, row in enumerate(rows):
        shard, offset = divmod(int(row), 16)
        images = np.load(dataset_dir / f"shard-{shard:05d}.images.npy")
        labels = np.load(dataset_dir / f"shard-{shard:05d}.labels.npy")
        np.testing.assert_array_equal(batch.images[position], images[offset])
        np.testing.assert_array_equal(batch.labels[position], labels[offset])
    np.testing.assert_array_equal(batch.indices, rows)
    np.testing.assert_array_equal(dataset.read_labels(rows), batch.labels)


def test_several_folders_read_as_one_folder_after_the_other(dataset_dir: Path, tmp_path: Path) -> None:
    other = CMVAEDataset(write_dataset(tmp_path / "other", count=20, seed=8, shard_size=7))
    first = CMVAEDataset(dataset_dir)
    union = open_datasets([str(dataset_dir), str(other.root)])
    assert isinstance(union, DatasetUnion) and len(union) == 70 and union.seed == 4
    rows = np.array([69, 0, 50, 49, 12, 55])  # across both folders, out of order
    batch = union.read(rows)
    expected = [other.read(np.array([19])), first.read(np.array([0])), other.read(np.array([0])),
                first.read(np.array([49])), first.read(np.array([12])), other.read(np.array([5]))]  # fmt: skip
    np.testing.assert_array_equal(batch.images, np.concatenate([part.images for part in expected]))
    np.testing.assert_array_equal(union.read_labels(rows), np.concatenate([part.labels for part in expected]))
    np.testing.assert_array_equal(batch.indices, rows)
    assert union.read_poses(rows).shape == (6, 12)
    with pytest.raises(IndexError, match=r"\[0, 70\)"):
        union.read(np.array([70]))
    assert isinstance(open_datasets(str(dataset_dir)), CMVAEDataset)  # one folder stays a plain dataset


def test_shards_are_memory_mapped_not_loaded(dataset_dir: Path) -> None:
    dataset = CMVAEDataset(dataset_dir)
    assert all(isinstance(images, np.memmap) for images in dataset._images)


def test_out_of_range_rows_are_refused(dataset_dir: Path) -> None:
    with pytest.raises(IndexError, match=r"\[0, 50\)"):
        CMVAEDataset(dataset_dir).read(np.array([3, 50]))


def _copy_with(dataset_dir: Path, target: Path, **changes: object) -> Path:
    target.mkdir()
    for path in dataset_dir.iterdir():
        (target / path.name).write_bytes(path.read_bytes())
    meta = json.loads((dataset_dir / "meta.json").read_text())
    meta.update(changes)
    (target / "meta.json").write_text(json.dumps(meta))
    return target


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"format": "something-else"}, "format is 'something-else'"),
        ({"version": 2}, "version is 2, expected 1"),
        ({"image_shape": [128, 128, 3]}, r"image_shape is \[128, 128, 3\]"),
        ({"label_names": ["d", "theta"]}, "label_names"),
        ({"count": 51}, "count=51 but the shards hold 50"),
        ({"shards": ["shard-00000", "shard-00009"]}, "shard-00009.images.npy is missing"),
        ({"shards": []}, "non-empty list"),
    ],
)
def test_bad_meta_is_refused_with_the_problem_named(
    dataset_dir: Path, tmp_path: Path, changes: dict, message: str
) -> None:
    with pytest.raises(DatasetFormatError, match=message):
        CMVAEDataset(_copy_with(dataset_dir, tmp_path / "bad", **changes))


def test_wrong_array_shape_or_dtype_is_refused(dataset_dir: Path, tmp_path: Path) -> None:
    bad = _copy_with(dataset_dir, tmp_path / "bad")
    np.save(bad / "shard-00001.images.npy", np.zeros((16, 64, 64, 3), dtype=np.float32))
    with pytest.raises(DatasetFormatError, match="expected uint8 .* got float32"):
        CMVAEDataset(bad)
    np.save(bad / "shard-00001.images.npy", np.zeros((16, 64, 64, 3), dtype=np.uint8))
    np.save(bad / "shard-00001.labels.npy", np.zeros((15, 3), dtype=np.float32))
    with pytest.raises(DatasetFormatError, match="16 images but 15 labels"):
        CMVAEDataset(bad)


def test_missing_folder_names_the_command_that_makes_one(tmp_path: Path) -> None:
    with pytest.raises(DatasetFormatError, match="swimm dataset"):
        CMVAEDataset(tmp_path / "nowhere")


def test_split_is_deterministic_disjoint_and_complete() -> None:
    train, val = split_indices(1000, 0.1, seed=7)
    assert len(train) == 900 and len(val) == 100
    assert np.intersect1d(train, val).size == 0
    np.testing.assert_array_equal(np.union1d(train, val), np.arange(1000))
    again_train, again_val = split_indices(1000, 0.1, seed=7)
    np.testing.assert_array_equal(val, again_val)
    assert not np.array_equal(val, split_indices(1000, 0.1, seed=8)[1])
    with pytest.raises(ValueError, match="keep both parts non-empty"):
        split_indices(3, 0.1, seed=0)


def test_batches_cover_every_row_once_and_shuffle_by_seed(dataset_dir: Path) -> None:
    dataset = CMVAEDataset(dataset_dir)
    rows = np.arange(50)
    ordered = [batch.indices for batch in iter_batches(dataset, rows, 16)]
    assert [len(part) for part in ordered] == [16, 16, 16, 2]
    np.testing.assert_array_equal(np.concatenate(ordered), rows)
    epoch0 = np.concatenate([batch.indices for batch in iter_batches(dataset, rows, 16, (0, 0))])
    epoch0_again = np.concatenate([batch.indices for batch in iter_batches(dataset, rows, 16, (0, 0))])
    epoch1 = np.concatenate([batch.indices for batch in iter_batches(dataset, rows, 16, (0, 1))])
    np.testing.assert_array_equal(epoch0, epoch0_again)
    assert not np.array_equal(epoch0, epoch1) and not np.array_equal(epoch0, rows)
    np.testing.assert_array_equal(np.sort(epoch1), rows)
    assert len(list(iter_batches(dataset, rows, 16, max_batches=2))) == 2
    assert count_batches(50, 16) == 4 and count_batches(50, 16, max_batches=2) == 2


def test_prefetch_keeps_order_and_passes_errors_through() -> None:
    assert list(prefetch(iter(range(100)), depth=3)) == list(range(100))

    def failing():
        yield 1
        raise RuntimeError("disk gone")

    consumed = []
    with pytest.raises(RuntimeError, match="disk gone"):
        for item in prefetch(failing()):
            consumed.append(item)
    assert consumed == [1]


def test_prefetch_stops_its_thread_when_the_consumer_leaves_early() -> None:
    import threading

    before = threading.active_count()
    stream = prefetch(iter(range(1000)), depth=2)
    assert next(stream) == 0
    stream.close()
    assert threading.active_count() == before


def test_a_dataset_rendered_by_the_sim_reads_back_with_labels_in_range(tmp_path: Path) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; read when MuJoCo is first imported
    from sim_service.dataset import write_dataset as render_dataset

    dataset = CMVAEDataset(render_dataset(tmp_path / "real", count=64, seed=11, shard_size=24, progress=False))
    assert len(dataset) == 64 and len(dataset.meta["shards"]) == 3
    batch = dataset.read(np.arange(64))
    d, theta, psi = batch.labels.T
    assert d.min() >= 2.0 and d.max() <= 10.0
    assert np.abs(theta).max() <= 39.99 and np.abs(psi).max() <= 180.0
    assert batch.images.std() > 5  # real pictures, not blank frames
