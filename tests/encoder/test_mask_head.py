"""The mask head: where the dolphin is, learnt beside the latent from sim frames' masks, and absent at inference."""

from __future__ import annotations

import json
import os
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.data import CMVAEDataset, DatasetFormatError, DatasetUnion, require_masks
from encoder_service.export import export_checkpoint
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, MaskHead, images_to_tensor, load_model, make_checkpoint, pool_masks
from encoder_service.train import mirror_batch, run
from tests.encoder.quick_training import quick_settings

SHIPPED = Path(__file__).parents[2] / "encoder_service" / "models" / "cmvae_general.pt"


def _sim_dataset(root: Path, masks: bool) -> Path:
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; read when MuJoCo is first imported
    from sim_service.dataset import write_dataset

    return write_dataset(root, count=96, seed=3, shard_size=40, progress=False, masks=masks)


@pytest.fixture(scope="module")
def masked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sim_dataset(tmp_path_factory.mktemp("mask-head") / "masked", masks=True)


@pytest.fixture(scope="module")
def unmasked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sim_dataset(tmp_path_factory.mktemp("mask-head") / "unmasked", masks=False)


_settings = partial(quick_settings, bn_batches=2)


def _column_side(masks: np.ndarray) -> np.ndarray:
    """+1 where the mask's pixels lie mostly left of the image centre (positive azimuth), -1 right."""
    columns = np.arange(masks.shape[2]) + 0.5
    centroid = (masks.sum(axis=1) * columns).sum(axis=1) / masks.sum(axis=(1, 2))
    return np.sign(masks.shape[2] / 2 - centroid)


def test_batches_carry_masks_only_where_the_dataset_has_them(masked: Path, unmasked: Path) -> None:
    batch = CMVAEDataset(masked).read(np.array([90, 3, 41]))
    assert batch.masks is not None and batch.masks.shape == (3, 64, 64) and batch.masks.dtype == bool
    np.testing.assert_array_equal(batch.masks[1], np.load(masked / "shard-00000.masks.npy")[3])
    assert CMVAEDataset(unmasked).read(np.array([0])).masks is None
    assert DatasetUnion([CMVAEDataset(masked), CMVAEDataset(masked)]).read(np.array([0, 100])).masks.shape[0] == 2
    with pytest.raises(DatasetFormatError, match=f"{unmasked}.*swimm dataset --masks"):
        require_masks(DatasetUnion([CMVAEDataset(masked), CMVAEDataset(unmasked)]), "--mask-weight")


def test_mirroring_flips_each_mask_with_its_frame_and_both_agree_with_theta(masked: Path) -> None:
    batch = CMVAEDataset(masked).read(np.arange(96))
    flip = np.arange(96) % 2 == 0
    mirrored = mirror_batch(batch, flip)
    np.testing.assert_array_equal(mirrored.masks[flip], batch.masks[flip, :, ::-1])
    np.testing.assert_array_equal(mirrored.masks[~flip], batch.masks[~flip])
    for view in (batch, mirrored):  # the dolphin's pixels sit on the side its azimuth says, flipped or not
        clear = np.abs(view.labels[:, 1]) > 5.0
        assert (_column_side(view.masks[clear]) == np.sign(view.labels[clear, 1])).mean() > 0.95


def test_the_head_changes_no_latent_and_never_reaches_inference(masked: Path, tmp_path: Path) -> None:
    torch.manual_seed(0)
    with_head = CMVAE(mask_head=True).eval()
    checkpoint = make_checkpoint(with_head, beta=8.0, epoch=1, val_loss=1.0, metrics={})
    torch.save(checkpoint, tmp_path / "head.pt")
    without = {name: tensor for name, tensor in checkpoint["state_dict"].items() if not name.startswith("mask_head.")}
    headless = CMVAE().eval()
    headless.load_state_dict(without)
    torch.save(make_checkpoint(headless, beta=8.0, epoch=1, val_loss=1.0, metrics={}), tmp_path / "headless.pt")

    images = images_to_tensor(CMVAEDataset(masked).read(np.arange(8)).images)
    with torch.no_grad():
        outputs = with_head(images)
        np.testing.assert_array_equal(outputs.mu.numpy(), headless(images).mu.numpy())
    assert outputs.mask.shape == (8, MaskHead.SIZE, MaskHead.SIZE)

    loaded, config = load_model(tmp_path / "head.pt")
    assert config["config"]["mask_head"] is True and loaded.mask_head is not None
    frames = CMVAEDataset(masked).read(np.arange(8)).images
    for engine in ("torch", "onnx"):
        mu_head, _ = LatentEncoder(tmp_path / "head.pt", engine=engine).encode(frames)
        mu_headless, _ = LatentEncoder(tmp_path / "headless.pt", engine=engine).encode(frames)
        np.testing.assert_array_equal(mu_head, mu_headless)
    shipped = torch.load(export_checkpoint(tmp_path / "head.pt", tmp_path / "shipped.pt"), weights_only=True)
    assert shipped["config"]["mask_head"] is False and not any(
        name.startswith("mask_head.") for name in shipped["state_dict"]
    )


def test_pooling_marks_a_cell_where_any_of_its_pixels_shows_the_dolphin() -> None:
    masks = torch.zeros(1, 64, 64, dtype=torch.bool)
    masks[0, 17, 63] = True
    pooled = pool_masks(masks, 8)
    assert pooled.sum() == 1 and pooled[0, 2, 7] == 1


def test_training_with_a_mask_weight_records_the_head_and_its_loss_falls(masked: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert run(_settings(masked, out, epochs=4, mask_weight=1.0, lr=1e-3)) == 0
    history = json.loads((out / "train_summary.json").read_text())["history"]
    assert history[-1]["train_mask"] < history[0]["train_mask"]
    best = torch.load(out / "best.pt", weights_only=True)
    assert best["config"]["mask_head"] is True and "mask_head.layers.1.weight" in best["state_dict"]
    assert {"mask", "mask_iou"} <= set(best["metrics"]) and 0.0 <= best["metrics"]["mask_iou"] <= 1.0
    assert (out / "masks.png").stat().st_size > 0  # frames, true and predicted masks


def test_masks_on_disk_change_nothing_without_a_mask_weight(masked: Path, unmasked: Path, tmp_path: Path) -> None:
    for dataset, out in ((masked, tmp_path / "masked"), (unmasked, tmp_path / "unmasked")):
        assert run(_settings(dataset, out, max_batches_per_epoch=2)) == 0
    weights = [
        torch.load(out / "last.pt", weights_only=True)["state_dict"]
        for out in (tmp_path / "masked", tmp_path / "unmasked")
    ]
    assert weights[0].keys() == weights[1].keys() and not any(name.startswith("mask_head.") for name in weights[0])
    for name, tensor in weights[0].items():
        assert torch.equal(tensor, weights[1][name]), name


def test_a_head_starts_fresh_on_a_shipped_model_without_one(masked: Path, tmp_path: Path) -> None:
    assert "mask_head" not in torch.load(SHIPPED, weights_only=True)["config"]  # shipped before the head existed
    out = tmp_path / "fine-tune"
    settings = _settings(masked, out, init=str(SHIPPED), mask_weight=0.5, max_batches_per_epoch=1)
    settings.input_norm = torch.load(SHIPPED, weights_only=True)["config"].get("input_norm", "none")
    assert run(settings) == 0
    assert torch.load(out / "best.pt", weights_only=True)["config"]["mask_head"] is True


def test_refusals_name_the_flag(masked: Path, unmasked: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--mask-weight must be a finite weight >= 0"):
        run(_settings(masked, tmp_path / "a", mask_weight=-1.0))
    with pytest.raises(DatasetFormatError, match=f"--mask-weight needs the dolphin's masks, but {unmasked}"):
        run(_settings(unmasked, tmp_path / "b", mask_weight=1.0))


def test_a_distilled_student_learns_the_masks_too(tmp_path: Path) -> None:
    from sim_service.dataset import write_dataset
    from sim_service.noise import NoiseSettings
    from sim_service.settings import WorldSettings

    noisy = WorldSettings(noise=NoiseSettings(preset="harsh", randomise=True))
    paired = write_dataset(tmp_path / "paired", count=48, seed=3, world_settings=noisy, progress=False, paired=True,
                           masks=True)  # fmt: skip
    out = tmp_path / "distilled"
    settings = _settings(paired, out, teacher=str(SHIPPED), mask_weight=1.0, max_batches_per_epoch=1)
    settings.input_norm = torch.load(SHIPPED, weights_only=True)["config"].get("input_norm", "none")
    assert run(settings) == 0
    best = torch.load(out / "best.pt", weights_only=True)
    assert best["config"]["mask_head"] is True and {"latent", "mask", "mask_iou", "clean_mask_iou"} <= set(
        best["metrics"]
    )
