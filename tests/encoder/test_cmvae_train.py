"""Real training runs on 128 frames rendered by the sim: loss falls, safe checkpoints, resume, early stopping."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.data import Batch, CMVAEDataset, DatasetFormatError, split_indices
from encoder_service.inference import DEFAULT_CHECKPOINT
from encoder_service.model import CMVAE, StateLoss, load_model
from encoder_service.train import (
    REVIVED_STD,
    EarlyStopping,
    TrainEncoderSettings,
    inputs_and_targets,
    mirror_batch,
    recalibrate_batch_norm,
    run,
    shift_batch,
    validate,
)

VERTICAL_CHECKPOINT = DEFAULT_CHECKPOINT.with_name("cmvae_vertical.pt")


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; read when MuJoCo is first imported
    from sim_service.dataset import write_dataset

    return write_dataset(
        tmp_path_factory.mktemp("cmvae-train") / "frames", count=128, seed=3, shard_size=48, progress=False
    )


def _settings(dataset_dir: Path, out: Path, **overrides: object) -> TrainEncoderSettings:
    base = {
        "dataset": str(dataset_dir),
        "out": str(out),
        "epochs": 2,
        "val_fraction": 0.25,
        "device": "cpu",
        "tensorboard": False,
    }
    return TrainEncoderSettings(**{**base, **overrides})


def _summary(out: Path) -> dict:
    return json.loads((out / "train_summary.json").read_text())


def test_two_epochs_lower_the_validation_loss_and_write_safe_checkpoints(dataset_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert run(_settings(dataset_dir, out, tensorboard=True)) == 0
    summary = _summary(out)
    assert summary["dataset_count"] == 128 and summary["train_count"] == 96 and summary["val_count"] == 32
    assert summary["epochs_run"] == 2 and summary["wall_time_s"] > 0
    assert summary["provenance"]["seeds"] == [summary["settings"]["seed"]] and "git" in summary["provenance"]
    first, second = summary["history"]
    assert second["val_loss"] < first["val_loss"]
    assert summary["best_epoch"] == 2 and summary["best_val_loss"] == pytest.approx(second["val_loss"])

    best = torch.load(out / "best.pt", weights_only=True)
    last = torch.load(out / "last.pt", weights_only=True)
    assert best["format"] == "swimm-cmvae" and best["version"] == 1
    assert best["config"] == {
        "n_z": 10,
        "beta": 8.0,
        "input_norm": "none",
        "mask_head": False,
        "labels": ["d", "theta", "psi"],
        "locate": False,
        "track": False,
        "mirror_average": False,
        "prior_distance": False,
        "circular_psi": False,
    }
    assert best["epoch"] == 2 and best["val_loss"] == pytest.approx(second["val_loss"])
    assert set(best["metrics"]) >= {"total", "image", "state", "kl", "mae_d", "mae_theta", "mae_psi"}
    assert "optimizer" not in best  # only last.pt carries the resume state
    steps = {float(state["step"]) for state in last["optimizer"]["state"].values()}
    assert steps == {6.0}  # 96 training rows / batch 32 = 3 Adam steps per epoch, 2 epochs
    assert any((out / "tb").iterdir())  # TensorBoard event file


def test_resume_continues_from_the_last_epoch_and_matches_an_uninterrupted_run_and_only_resume_reuses_a_folder(
    dataset_dir: Path, tmp_path: Path
) -> None:
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    run(_settings(dataset_dir, straight))
    run(_settings(dataset_dir, resumed, epochs=1))
    assert torch.load(resumed / "last.pt", weights_only=True)["epoch"] == 1
    before = (resumed / "train_summary.json").read_bytes()
    with pytest.raises(
        FileExistsError, match=r"--out .* already holds a training run \(last.pt, best.pt\): --resume goes on with it"
    ):
        run(_settings(dataset_dir, resumed, epochs=2))  # a new run would overwrite the first one's files
    assert (resumed / "train_summary.json").read_bytes() == before
    run(_settings(dataset_dir, resumed, epochs=2, resume=True))
    summary = _summary(resumed)
    assert summary["start_epoch"] == 2 and summary["epochs_run"] == 1 and summary["last_epoch"] == 2
    a = torch.load(straight / "last.pt", weights_only=True)
    b = torch.load(resumed / "last.pt", weights_only=True)
    assert b["epoch"] == 2
    assert b["val_loss"] == pytest.approx(a["val_loss"], rel=1e-5)
    for name, tensor in a["state_dict"].items():
        torch.testing.assert_close(b["state_dict"][name], tensor, rtol=1e-5, atol=1e-6)


def test_keep_epochs_writes_each_epochs_weights_and_the_last_equals_last_pt(dataset_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "kept"
    run(_settings(dataset_dir, out, keep_epochs=True))
    first = torch.load(out / "epoch-1.pt", weights_only=True)
    second = torch.load(out / "epoch-2.pt", weights_only=True)
    last = torch.load(out / "last.pt", weights_only=True)
    assert (first["epoch"], second["epoch"]) == (1, 2) and "optimizer" not in second
    for name, tensor in last["state_dict"].items():
        assert torch.equal(second["state_dict"][name], tensor)
    assert any(not torch.equal(first["state_dict"][name], tensor) for name, tensor in last["state_dict"].items())
    assert not (tmp_path / "plain").exists()
    run(_settings(dataset_dir, tmp_path / "plain", epochs=1))
    assert not list((tmp_path / "plain").glob("epoch-*.pt"))  # off by default


def test_init_starts_from_a_checkpoints_weights(dataset_dir: Path, tmp_path: Path) -> None:
    """--init loads the shipped float16 file; with lr 0 the learned weights stay exactly the shipped ones."""
    out = tmp_path / "fine-tune"
    run(_settings(dataset_dir, out, epochs=1, lr=0.0, init=str(DEFAULT_CHECKPOINT)))
    shipped = torch.load(DEFAULT_CHECKPOINT, weights_only=True)["state_dict"]
    tuned = torch.load(out / "last.pt", weights_only=True)
    assert tuned["epoch"] == 1  # a fine-tune counts its own epochs
    for name, _ in CMVAE().named_parameters():  # buffers (batch-norm statistics) do move in training mode
        torch.testing.assert_close(tuned["state_dict"][name], shipped[name].float(), rtol=0, atol=0)
    with pytest.raises(ValueError, match="n_z"):
        run(_settings(dataset_dir, tmp_path / "wrong", epochs=1, n_z=8, init=str(DEFAULT_CHECKPOINT)))


def test_a_mirrored_frame_is_the_frame_of_the_mirrored_pose() -> None:
    """Flipping a frame and negating theta and psi gives what the camera sees of the reflected scene."""
    from sim_service.world import World

    world = World()
    try:
        rover = np.array([0.0, 0.0, -4.0])  # at the origin facing +x: the mirror plane is y = 0

        def frame(theta_deg: float, psi_deg: float, d: float = 4.0) -> np.ndarray:
            bearing = math.radians(theta_deg)
            target = rover + d * np.array([math.cos(bearing), math.sin(bearing), 0.0])
            return world.place(rover, 0.0, target, math.radians(psi_deg))[1]

        for theta, psi in ((20.0, 60.0), (-30.0, 150.0)):
            batch = Batch(
                images=frame(theta, psi)[None],
                labels=np.array([[4.0, theta, psi]], np.float32),
                indices=np.zeros(1, np.int64),
            )
            mirrored = mirror_batch(batch, np.array([True]))
            np.testing.assert_allclose(mirrored.labels, [[4.0, -theta, -psi]])
            with_elevation = replace(batch, labels=np.array([[4.0, theta, psi, 12.0]], np.float32))
            np.testing.assert_allclose(
                mirror_batch(with_elevation, np.array([True])).labels, [[4.0, -theta, -psi, 12.0]]
            )
            truth = frame(-theta, -psi).astype(int)
            flipped_error = np.abs(mirrored.images[0].astype(int) - truth).mean()
            unflipped_error = np.abs(batch.images[0].astype(int) - truth).mean()
            assert flipped_error < 0.5 and flipped_error < 0.2 * unflipped_error  # the sun is a little off-axis
            assert np.array_equal(mirror_batch(batch, np.array([False])).images, batch.images)
    finally:
        world.close()


def test_a_shifted_frame_is_the_frame_of_a_camera_turned_by_its_angle() -> None:
    """Moving a frame s pixels right and turning theta and psi by atan(tan(theta) - s / f) - theta gives what the
    camera sees once the rover has turned left by that angle."""
    from sim_service.world import World

    world = World()
    try:
        rover = np.array([0.0, 0.0, -4.0])
        theta, psi, d = 8.0, 60.0, 5.0
        bearing = math.radians(theta)
        target = rover + d * np.array([math.cos(bearing), math.sin(bearing), 0.0])
        frame = world.place(rover, 0.0, target, math.radians(psi))[1]
        batch = Batch(
            images=np.stack([frame, frame]),
            labels=np.array([[d, theta, psi, 5.0]] * 2, np.float32),
            indices=np.arange(2),
            masks=np.ones((2, 64, 64), bool),
        )
        shifted = shift_batch(batch, np.array([3, 0]))
        focal_px = 32 / math.tan(math.radians(39.9758))  # half the 64-pixel width over tan(alpha)
        turned = math.degrees(math.atan(math.tan(math.radians(theta)) - 3 / focal_px))
        np.testing.assert_allclose(shifted.labels[0], [d, turned, psi + turned - theta, 5.0], atol=1e-4)
        assert turned == pytest.approx(3.545, abs=0.005)  # by hand: atan(tan(8 deg) - 3 / 38.19), 1.5 deg a pixel
        np.testing.assert_array_equal(shifted.labels[1], batch.labels[1])
        np.testing.assert_array_equal(shifted.images[1], frame)
        assert not shifted.masks[0][:, :3].any() and shifted.masks[0][:, 3:].all()  # no dolphin where none was drawn

        # The turned camera's frame is nearest the frame moved by 3 pixels, of all moves from -5 to 5 (the water's
        # shading turns with the camera too, so not equal to it).
        truth = world.place(rover, math.radians(theta - turned), target, math.radians(psi))[1].astype(int)
        errors = {
            pixels: np.abs(shift_batch(batch, np.array([pixels, 0])).images[0].astype(int) - truth)[:, 5:-5].mean()
            for pixels in range(-5, 6)
        }
        assert min(errors, key=errors.get) == 3 and errors[3] < 0.6 * errors[0], errors
    finally:
        world.close()


def test_shifted_training_runs_and_a_shift_past_a_quarter_frame_is_refused(dataset_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "shifted"
    assert run(_settings(dataset_dir, out, epochs=1, shift_pixels=3)) == 0
    assert _summary(out)["settings"]["shift_pixels"] == 3
    with pytest.raises(ValueError, match="--shift-pixels must be 0 \\(off\\) to 16, got 17"):
        run(_settings(dataset_dir, tmp_path / "refused", shift_pixels=17))


def test_batch_norm_statistics_are_re_estimated_at_the_final_weights(dataset_dir: Path) -> None:
    """After recalibration, eval mode (running statistics) answers as train mode (this batch's) does."""
    from encoder_service.data import CMVAEDataset
    from encoder_service.model import images_to_tensor

    dataset = CMVAEDataset(dataset_dir)
    rows = np.arange(len(dataset))
    images = images_to_tensor(dataset.read(rows).images)
    torch.manual_seed(0)
    model = CMVAE()
    for layer in model.modules():
        if isinstance(layer, torch.nn.BatchNorm2d):
            layer.running_mean.fill_(3.0)  # statistics of weights long gone
    settings = TrainEncoderSettings(batch_size=len(rows), bn_batches=1)

    def eval_vs_train_gap() -> float:
        with torch.no_grad():
            model.eval()
            evaluated = model(images).mu
            model.train()
            trained = model(images, sample=False).mu
        return float((evaluated - trained).abs().max())

    assert eval_vs_train_gap() > 0.1
    recalibrate_batch_norm(model, dataset, rows, settings, epoch=0, device=torch.device("cpu"))
    assert eval_vs_train_gap() < 1e-2  # the stored variance is unbiased, the batch's is not: not exactly 0
    assert all(layer.momentum == 0.1 for layer in model.modules() if isinstance(layer, torch.nn.BatchNorm2d))


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_keeps_the_finished_epochs_and_writes_the_summary(
    dataset_dir: Path, tmp_path: Path, stop_signal: signal.Signals
) -> None:
    """SIGINT or SIGTERM to a running `swimm train-encoder`: exit 130, checkpoints kept, a summary that says so."""
    out = tmp_path / "interrupted"
    command = [sys.executable, "-m", "swimm", "train-encoder", "--dataset", str(dataset_dir), "--out", str(out)]
    command += ["--epochs", "1000", "--val-fraction", "0.25", "--device", "cpu", "--no-tensorboard"]
    # As from a terminal: a test run started in the background by a script ignores SIGINT, and children inherit that.
    restore_ctrl_c = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=restore_ctrl_c)
    try:
        deadline = time.monotonic() + 120
        while not (out / "last.pt").is_file():
            assert process.poll() is None and time.monotonic() < deadline, process.stderr.read().decode()[-2000:]
            time.sleep(0.1)
        process.send_signal(stop_signal)
        assert process.wait(timeout=60) == 130
    finally:
        process.kill()
    summary = _summary(out)
    assert summary["interrupted"] is True and summary["stopped_early"] is False
    assert summary["epochs_run"] >= 1 and summary["best_epoch"] >= 1
    assert torch.load(out / "best.pt", weights_only=True)["epoch"] == summary["best_epoch"]


def test_early_stopping_ends_the_run_once_patience_runs_out(dataset_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "stops"
    # needing a 90% drop per epoch cannot be met, so epoch 2 spends the single epoch of patience
    run(_settings(dataset_dir, out, epochs=10, patience=1, min_rel_gain=0.9, max_batches_per_epoch=1))
    summary = _summary(out)
    assert summary["stopped_early"] is True and summary["epochs_run"] == 2


def test_early_stopping_counts_only_gains_of_the_required_size() -> None:
    stopper = EarlyStopping(patience=2, min_rel_gain=0.01)
    assert stopper.update(1.0) is False and stopper.reference == 1.0
    assert stopper.update(0.995) is False  # 0.5% better: not a gain, patience 1 of 2 spent
    assert stopper.reference == 1.0 and stopper.epochs_without_gain == 1
    assert stopper.update(0.98) is False  # 2% better than the reference: resets
    assert stopper.reference == 0.98 and stopper.epochs_without_gain == 0
    assert stopper.update(0.975) is False
    assert stopper.update(0.974) is True
    assert math.isinf(EarlyStopping(patience=1, min_rel_gain=0.01).reference)


def test_a_missing_dataset_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--dataset"):
        run(TrainEncoderSettings(out=str(tmp_path)))


def test_psi_loss_l1_trains_and_validates_on_the_absolute_error(dataset_dir: Path, tmp_path: Path) -> None:
    """With --psi-loss l1 the validation loss that early stopping and best.pt read is the l1 one."""
    out = tmp_path / "l1"
    settings = _settings(dataset_dir, out, epochs=1, psi_loss="l1")
    assert run(settings) == 0
    reported = _summary(out)["last_val_metrics"]["state"]
    model = CMVAE()
    model.load_state_dict(torch.load(out / "best.pt", weights_only=True)["state_dict"])
    _, val_rows = split_indices(128, settings.val_fraction, settings.seed)
    dataset = CMVAEDataset(str(dataset_dir))
    device = torch.device("cpu")
    state = {
        loss: validate(model, dataset, val_rows, settings.batch_size, settings.beta, device, StateLoss(loss))["state"]
        for loss in ("l1", "mse")
    }
    assert reported == pytest.approx(state["l1"], rel=1e-5)
    assert state["l1"] > state["mse"]  # |error| > error**2 for normalised psi errors under 1
    with pytest.raises(ValueError, match="--psi-loss"):
        run(_settings(dataset_dir, tmp_path / "bad", psi_loss="huber"))
    with pytest.raises(ValueError, match="--state-weights"):
        run(_settings(dataset_dir, tmp_path / "bad", state_weights=[1.0, -1.0, 1.0]))
    assert not (tmp_path / "bad").exists()  # refused before anything was written
    with pytest.raises(ValueError, match="elevation's weight needs a --vertical dataset"):
        run(_settings(dataset_dir, tmp_path / "planar", state_weights=[1.0, 1.0, 1.0, 4.0]))
    assert not (tmp_path / "planar" / "last.pt").exists()  # refused before the first epoch


@pytest.fixture(scope="module")
def paired_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from sim_service.dataset import write_dataset
    from sim_service.noise import NoiseSettings
    from sim_service.settings import WorldSettings

    noisy = WorldSettings(noise=NoiseSettings(preset="harsh", randomise=True))
    return write_dataset(tmp_path_factory.mktemp("cmvae-paired") / "frames", count=96, seed=3, shard_size=40,
                         world_settings=noisy, progress=False, paired=True)  # fmt: skip


def test_a_paired_batch_feeds_the_chosen_frames_and_always_targets_the_clean_one(paired_dir: Path) -> None:
    dataset = CMVAEDataset(paired_dir)
    assert dataset.paired
    batch = mirror_batch(dataset.read(np.arange(6)), np.array([True, False] * 3))
    assert batch.clean is not None and not np.array_equal(batch.clean, batch.images)
    np.testing.assert_array_equal(batch.clean[0], dataset.read(np.array([0])).clean[0][:, ::-1])  # flipped too
    feed_clean = np.array([True, True, False, False, True, False])
    inputs, targets = inputs_and_targets(batch, feed_clean)
    np.testing.assert_array_equal(inputs[feed_clean], batch.clean[feed_clean])
    np.testing.assert_array_equal(inputs[~feed_clean], batch.images[~feed_clean])
    np.testing.assert_array_equal(targets, batch.clean)
    unpaired = Batch(images=batch.images, labels=batch.labels, indices=batch.indices)
    assert inputs_and_targets(unpaired, feed_clean) == (unpaired.images, unpaired.images)


def test_training_on_a_paired_dataset_validates_noisy_and_clean_inputs(paired_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert run(_settings(paired_dir, out)) == 0
    metrics = _summary(out)["last_val_metrics"]
    assert {"mae_d", "clean_mae_d", "clean_total", "clean_image"} <= set(metrics)
    noisy_only = validate(*_validate_args(paired_dir, out))
    clean_only = validate(*_validate_args(paired_dir, out), feed_clean=True)
    assert metrics["total"] == pytest.approx((noisy_only["total"] + clean_only["total"]) / 2, rel=1e-5)
    assert metrics["mae_d"] == pytest.approx(noisy_only["mae_d"], rel=1e-5)


def test_training_reads_several_folders_as_one(paired_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "union"
    assert run(_settings(paired_dir, out, dataset=[str(paired_dir), str(paired_dir)], epochs=1)) == 0
    summary = _summary(out)
    assert summary["dataset_count"] == 2 * len(CMVAEDataset(paired_dir))
    assert summary["settings"]["dataset"] == [str(paired_dir), str(paired_dir)]


def test_paired_and_unpaired_folders_are_not_mixed(paired_dir: Path, dataset_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(DatasetFormatError, match=f"cannot mix paired and unpaired.*{paired_dir}"):
        run(_settings(paired_dir, tmp_path / "mixed", dataset=[str(paired_dir), str(dataset_dir)]))
    assert not (tmp_path / "mixed" / "last.pt").exists()


def test_a_paired_dataset_missing_its_clean_shard_is_refused(paired_dir: Path, tmp_path: Path) -> None:
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(paired_dir, broken)
    (broken / "shard-00001.clean.npy").unlink()
    with pytest.raises(DatasetFormatError, match="paired.*shard-00001.clean.npy"):
        CMVAEDataset(broken)


def _validate_args(dataset_dir: Path, out: Path) -> tuple:
    from encoder_service.model import read_checkpoint

    dataset = CMVAEDataset(dataset_dir)
    _, val_rows = split_indices(len(dataset), 0.25, 0)
    model = CMVAE()
    model.load_state_dict(read_checkpoint(out / "last.pt")["state_dict"])
    return model, dataset, val_rows, 32, 8.0, torch.device("cpu")


def _latent_match(model: CMVAE, teacher: CMVAE, dataset: CMVAEDataset, rows: np.ndarray) -> float:
    """Validation's latent term on ``rows`` read noisy: the distance to the teacher's latent of the clean twins."""
    return validate(model, dataset, rows, 32, 8.0, torch.device("cpu"), teacher=teacher)["latent"]


def test_distillation_pulls_noisy_latents_to_the_teachers_clean_ones_and_keeps_its_decoders(
    paired_dir: Path, tmp_path: Path
) -> None:
    from encoder_service.model import load_model, read_checkpoint

    out = tmp_path / "run"
    settings = _settings(paired_dir, out, teacher=str(DEFAULT_CHECKPOINT), epochs=3, lr=1e-3, clean_share=0.0)
    assert run(settings) == 0
    teacher, _ = load_model(DEFAULT_CHECKPOINT)
    student = CMVAE()
    student.load_state_dict(read_checkpoint(out / "last.pt")["state_dict"])
    dataset = CMVAEDataset(paired_dir)
    train_rows, _ = split_indices(len(dataset), 0.25, 0)
    before, after = (
        _latent_match(teacher, teacher, dataset, train_rows),
        _latent_match(student, teacher, dataset, train_rows),
    )
    assert after < 0.7 * before, (before, after)
    frozen = [name for name in teacher.state_dict() if not name.startswith("encoder.")]
    assert frozen and all(torch.equal(student.state_dict()[n], teacher.state_dict()[n]) for n in frozen)
    assert not torch.equal(student.state_dict()["encoder.head.4.weight"], teacher.state_dict()["encoder.head.4.weight"])
    assert {"latent", "clean_latent", "mae_d", "clean_mae_d"} <= set(_summary(out)["last_val_metrics"])


def test_a_teacher_on_its_own_clean_frames_matches_exactly(paired_dir: Path) -> None:
    from encoder_service.model import load_model

    teacher, _ = load_model(DEFAULT_CHECKPOINT)
    dataset = CMVAEDataset(paired_dir)
    rows = np.arange(len(dataset))
    clean = validate(teacher, dataset, rows, 32, 8.0, torch.device("cpu"), feed_clean=True, teacher=teacher)
    assert clean["latent"] == pytest.approx(0.0, abs=1e-10)
    assert _latent_match(teacher, teacher, dataset, rows) > 0.01  # the noisy twins' latents do differ


def test_the_consistency_term_is_nought_for_an_unchanged_frame_and_grows_with_what_augmentation_moves(
    paired_dir: Path,
) -> None:
    from encoder_service.model import (
        add_consistency_loss,
        distillation_loss,
        images_to_tensor,
        load_model,
        normalise_labels,
    )

    student, _ = load_model(DEFAULT_CHECKPOINT)
    batch = CMVAEDataset(paired_dir).read(np.arange(16))
    plain = images_to_tensor(batch.images)
    labels = torch.from_numpy(normalise_labels(batch.labels, student.labels))
    teacher_mu, teacher_logvar = student.encode(images_to_tensor(batch.clean))

    def parts_for(images: torch.Tensor) -> tuple[dict[str, float], float]:
        parts = distillation_loss(student, images, teacher_mu, teacher_logvar, labels, 1.0)
        before = float(parts.total.detach())
        return add_consistency_loss(parts, student, plain, weight=5.0).as_floats(), before

    same, before = parts_for(plain)
    assert same["consistency"] == pytest.approx(0.0, abs=1e-12) and same["total"] == pytest.approx(before)
    darkened, before = parts_for(plain * 0.5)  # a look the frame did not have: the read moves
    assert darkened["consistency"] > 1e-4
    assert darkened["total"] == pytest.approx(before + 5.0 * darkened["consistency"], rel=1e-6)
    assert set(darkened) == {"total", "latent", "state", "consistency"}


def test_a_consistency_run_trains_and_the_weight_is_refused_without_a_teacher_or_below_nought(
    paired_dir: Path, dataset_dir: Path, tmp_path: Path
) -> None:
    settings = _settings(paired_dir, tmp_path / "held", teacher=str(DEFAULT_CHECKPOINT), epochs=1,
                         augment_fans=1.0, consistency_weight=2.0)  # fmt: skip
    assert run(settings) == 0 and _summary(tmp_path / "held")["epochs_run"] == 1
    with pytest.raises(ValueError, match="--consistency-weight holds a distilled encoder's reads: give --teacher"):
        run(_settings(dataset_dir, tmp_path / "untaught", consistency_weight=1.0))
    with pytest.raises(ValueError, match="--consistency-weight must be a weight >= 0"):
        run(_settings(paired_dir, tmp_path / "negative", teacher=str(DEFAULT_CHECKPOINT), consistency_weight=-1.0))
    assert not (tmp_path / "untaught").exists() and not (tmp_path / "negative").exists()


def test_distillation_needs_a_paired_dataset(dataset_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--teacher needs a paired dataset"):
        run(_settings(dataset_dir, tmp_path / "run", teacher=str(DEFAULT_CHECKPOINT)))


@pytest.fixture(scope="module")
def vertical_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from sim_service.dataset import VERTICAL_RANGES, write_dataset

    root = tmp_path_factory.mktemp("cmvae-vertical") / "frames"
    return write_dataset(root, count=64, seed=3, shard_size=32, progress=False, ranges=VERTICAL_RANGES)


def test_a_vertical_dataset_trains_an_elevation_decoder_on_a_planar_models_encoder(
    vertical_dir: Path, tmp_path: Path
) -> None:
    """--init from the shipped planar model: its weights carry over, z[3] gains a fresh decoder for the elevation."""
    out = tmp_path / "vertical"
    run(_settings(vertical_dir, out, epochs=1, lr=0.0, init=str(DEFAULT_CHECKPOINT)))
    shipped = torch.load(DEFAULT_CHECKPOINT, weights_only=True)["state_dict"]
    tuned = torch.load(out / "last.pt", weights_only=True)
    assert tuned["config"]["labels"] == ["d", "theta", "psi", "elevation"]
    assert "mae_elevation" in tuned["metrics"] and tuned["metrics"]["mae_elevation"] > 0
    last_layer = "encoder.head.4."
    for name, _ in CMVAE().named_parameters():
        if not name.startswith(last_layer):
            torch.testing.assert_close(tuned["state_dict"][name], shipped[name].float(), rtol=0, atol=0)
    # every latent but z[3] (rows 3 and 3 + n_z of the last layer) keeps the planar model's mean and spread
    weight, bias = (tuned["state_dict"][last_layer + part] for part in ("weight", "bias"))
    kept = [row for row in range(20) if row not in (3, 13)]
    torch.testing.assert_close(weight[kept], shipped[last_layer + "weight"].float()[kept], rtol=0, atol=0)
    # z[3] restarts: a mean the planar model never had, a narrow spread whatever the frame
    assert not torch.equal(weight[3], shipped[last_layer + "weight"].float()[3])
    assert torch.count_nonzero(weight[13]) == 0 and bias[13].item() == pytest.approx(2 * math.log(REVIVED_STD))
    assert "state_decoders.3.mlp.0.weight" in tuned["state_dict"]
    model, _ = load_model(out / "last.pt")
    assert model.labels == ("d", "theta", "psi", "elevation") and model.decode_state(torch.zeros(2, 10)).shape == (2, 4)


def test_a_vertical_dataset_is_refused_where_its_labels_cannot_serve(
    dataset_dir: Path, vertical_dir: Path, tmp_path: Path
) -> None:
    with pytest.raises(DatasetFormatError, match="cannot mix datasets with different labels"):
        run(_settings(dataset_dir, tmp_path / "mixed", dataset=[str(dataset_dir), str(vertical_dir)], epochs=1))
    with pytest.raises(ValueError, match="--teacher needs a paired dataset"):
        run(_settings(vertical_dir, tmp_path / "distil", epochs=1, teacher=str(VERTICAL_CHECKPOINT)))


@pytest.fixture(scope="module")
def paired_vertical_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from sim_service.dataset import VERTICAL_RANGES, write_dataset
    from sim_service.noise import NoiseSettings
    from sim_service.settings import WorldSettings

    murky = WorldSettings(noise=NoiseSettings(preset="murky"))
    return write_dataset(tmp_path_factory.mktemp("cmvae-vertical-paired") / "frames", count=64, seed=3, shard_size=32,
                         world_settings=murky, ranges=VERTICAL_RANGES, progress=False, paired=True)  # fmt: skip


def test_a_vertical_dataset_distils_from_a_vertical_teacher_only(paired_vertical_dir: Path, tmp_path: Path) -> None:
    """The 3d task's CMVAE teaches its own labels: the student keeps its four decoders and learns the teacher's
    latents of the clean twins; a planar teacher, whose z[3] is no elevation, is refused by name."""
    from encoder_service.model import read_checkpoint

    with pytest.raises(ValueError, match=r"reads d, theta, psi; .* labels are d, theta, psi, elevation"):
        run(_settings(paired_vertical_dir, tmp_path / "planar", epochs=1, teacher=str(DEFAULT_CHECKPOINT)))
    out = tmp_path / "run"
    assert run(_settings(paired_vertical_dir, out, teacher=str(VERTICAL_CHECKPOINT), epochs=2, lr=1e-3)) == 0
    teacher, _ = load_model(VERTICAL_CHECKPOINT)
    student = read_checkpoint(out / "last.pt")
    assert student["config"]["labels"] == ["d", "theta", "psi", "elevation"]
    frozen = [name for name in teacher.state_dict() if name.startswith("state_decoders.")]
    assert any(name.startswith("state_decoders.3.") for name in frozen)
    assert all(torch.equal(student["state_dict"][name], teacher.state_dict()[name]) for name in frozen)
    assert "mae_elevation" in _summary(out)["last_val_metrics"]
