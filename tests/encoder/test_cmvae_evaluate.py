"""eval-encoder end to end on small synthetic datasets: metrics.json holds the paper's numbers, figures are PNGs."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from encoder_service.evaluate import EncodedSet, EvalEncoderSettings, psi_breakdown, run, state_metrics
from encoder_service.model import CMVAE, make_checkpoint
from services.results import file_sha256
from tests.encoder.cmvae_testdata import write_dataset

FIGURES = ["reconstructions.png", "interpolation.png", "latent_sweeps.png", "state_scatter.png"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cmvae-eval")
    torch.manual_seed(0)
    checkpoint = root / "cmvae.pt"
    torch.save(make_checkpoint(CMVAE(), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    return {
        "checkpoint": checkpoint,
        "clean": write_dataset(root / "clean", count=40, seed=5, shard_size=16),
        "noisy": write_dataset(root / "noisy", count=40, seed=5, shard_size=16, noise=40.0),
        "other": write_dataset(root / "other", count=40, seed=6, shard_size=16),
    }


def test_clean_and_noisy_metrics_and_figures(setup: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "eval"
    settings = EvalEncoderSettings(
        checkpoint=str(setup["checkpoint"]),
        dataset=str(setup["clean"]),
        out=str(out),
        noisy_dataset=str(setup["noisy"]),
        batch_size=16,
        max_images=30,
        device="cpu",
    )
    assert run(settings) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["count"] == 30 and metrics["n_z"] == 10 and metrics["dataset_seed"] == 5
    about = metrics["provenance"]  # what made the numbers: the encoder by its content hash, the frames' seed
    assert about["models"]["encoder"]["sha256"] == file_sha256(setup["checkpoint"]) and about["seeds"] == [5]
    assert set(metrics["mae"]) == {"d_m", "theta_deg", "psi_deg"}
    assert set(metrics["mae_normalised"]) == {"d", "theta", "psi"}
    assert 0 < metrics["mae"]["d_m"] <= 8 and 0 < metrics["mae"]["psi_deg"] <= 180
    assert metrics["mae_normalised"]["d"] == pytest.approx(metrics["mae"]["d_m"] / 8.0)
    assert metrics["mae_normalised"]["psi"] == pytest.approx(metrics["mae"]["psi_deg"] / 360.0)
    assert 0 < metrics["image_mae_255"] < 255
    assert len(metrics["latent_std"]) == 10
    assert 0 <= metrics["psi"]["median_deg"] <= 180 and 0 <= metrics["psi"]["reversed_share"] <= 1
    camera = metrics["camera_labels"]
    assert camera["theta_mae_rover_deg"] == pytest.approx(metrics["mae"]["theta_deg"], rel=1e-5)
    assert 0 < camera["gap_mean_abs_deg"] <= camera["gap_max_abs_deg"] < 6  # 0.235 m ahead, targets 2-10 m away
    assert 0 <= camera["theta_error_share_of_gap"] <= 1 and camera["theta_mae_camera_deg"] > 0

    noisy = metrics["noisy"]
    assert set(noisy["latent_drift"]) == {"z0", "z1", "z2"} and len(noisy["latent_drift_all"]) == 10
    assert all(value > 0 for value in noisy["latent_drift"].values())  # noise moves the latents
    assert noisy["latent_drift"]["z1"] == pytest.approx(noisy["latent_drift_all"][1])
    assert set(noisy["mae"]) == {"d_m", "theta_deg", "psi_deg"}
    assert noisy["image_mae_255"] > 0 and noisy["image_mae_255_vs_clean"] > 0

    for name in [*FIGURES, "noise_comparison.png", "latent_drift.png"]:
        assert (out / name).read_bytes()[:8] == PNG_MAGIC, name
        assert str(out / name) in metrics["figures"]


def test_identical_datasets_drift_by_exactly_zero(setup: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "same"
    run(
        EvalEncoderSettings(
            checkpoint=str(setup["checkpoint"]),
            dataset=str(setup["clean"]),
            out=str(out),
            noisy_dataset=str(setup["clean"]),
            batch_size=64,
            device="cpu",
        )
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["count"] == 40
    assert np.allclose(metrics["noisy"]["latent_drift_all"], 0.0, atol=1e-6)
    assert metrics["noisy"]["mae"] == pytest.approx(metrics["mae"])
    for name in FIGURES:
        assert (out / name).is_file()


def test_a_noisy_dataset_of_other_poses_is_refused(setup: dict[str, Path], tmp_path: Path) -> None:
    settings = EvalEncoderSettings(
        checkpoint=str(setup["checkpoint"]),
        dataset=str(setup["clean"]),
        out=str(tmp_path / "x"),
        noisy_dataset=str(setup["other"]),
        device="cpu",
    )
    with pytest.raises(ValueError, match="same seed"):
        run(settings)


def test_a_result_made_by_python_m_swimm_records_the_swimm_command(setup: dict[str, Path], tmp_path: Path) -> None:
    """`python -m swimm` (how a worktree snapshot runs its own code) records the command as `swimm ...`, as the
    console script does, so the recorded command reruns on any checkout."""
    out = tmp_path / "eval"
    args = ["eval-encoder", "--checkpoint", str(setup["checkpoint"]), "--dataset", str(setup["clean"]),
            "--out", str(out), "--max-images", "8", "--device", "cpu"]  # fmt: skip
    subprocess.run([sys.executable, "-m", "swimm", *args], check=True, capture_output=True, timeout=300)
    recorded = json.loads((out / "metrics.json").read_text())["provenance"]["command"]
    assert recorded == shlex.join(["swimm", *args])


def test_a_missing_checkpoint_names_the_command(setup: dict[str, Path], tmp_path: Path) -> None:
    settings = EvalEncoderSettings(
        checkpoint=str(tmp_path / "none.pt"), dataset=str(setup["clean"]), out=str(tmp_path / "x")
    )
    with pytest.raises(FileNotFoundError, match="swimm train-encoder"):
        run(settings)


def test_psi_breakdown_splits_the_error_by_view_and_distance() -> None:
    """Four frames with known errors: a side view off by 10 deg, a head-on view read the wrong way round, ..."""
    labels = np.array([[3.0, 0.0, 90.0], [9.0, 0.0, 10.0], [5.0, 0.0, -170.0], [9.5, 0.0, -100.0]])
    predicted = np.array([[3.0, 0.0, 100.0], [9.0, 0.0, -170.0], [5.0, 0.0, 170.0], [9.5, 0.0, -70.0]])
    encoded = EncodedSet(
        mu=np.zeros((4, 10)), predicted=predicted, labels=labels, image_mae=0.0, image_mae_vs_reference=None
    )
    breakdown = psi_breakdown(encoded)  # errors: 10, 180, 20 (the short way round 180), 30
    assert breakdown["median_deg"] == pytest.approx(25.0)
    assert breakdown["reversed_share"] == pytest.approx(0.25)
    assert breakdown["mae_by_view_deg"] == pytest.approx(
        {"head_on": 180.0, "oblique_front": None, "side": 20.0, "oblique_back": None, "from_behind": 20.0}
    )
    assert breakdown["mae_by_distance_deg"] == pytest.approx({"2-4m": 10.0, "4-6m": 20.0, "6-8m": None, "8-10m": 105.0})


def test_state_metrics_split_every_labels_error_by_distance_band() -> None:
    """Three frames with known errors in d, theta and psi, at 3, 5 and 5.5 m: the 4-6 m band averages two."""
    labels = np.array([[3.0, 10.0, 0.0], [5.0, -5.0, 170.0], [5.5, 0.0, 90.0]])
    predicted = np.array([[3.5, 12.0, 20.0], [4.0, -5.0, -170.0], [5.5, 3.0, 60.0]])
    encoded = EncodedSet(
        mu=np.zeros((3, 10)), predicted=predicted, labels=labels, image_mae=0.0, image_mae_vs_reference=None
    )
    metrics = state_metrics(encoded)
    assert metrics["mae"] == pytest.approx({"d_m": 0.5, "theta_deg": 5.0 / 3, "psi_deg": 70.0 / 3})
    bands = metrics["mae_by_distance"]
    assert set(bands) == {"2-4m", "4-6m"}  # no frame in the far bands
    assert bands["2-4m"] == pytest.approx({"d_m": 0.5, "theta_deg": 2.0, "psi_deg": 20.0})
    assert bands["4-6m"] == pytest.approx({"d_m": 0.5, "theta_deg": 1.5, "psi_deg": 25.0})


def test_the_elevation_is_read_by_a_vertical_model_and_left_out_by_a_planar_one_or_on_planar_frames(
    setup: dict[str, Path], tmp_path: Path
) -> None:
    from services.geometry import VERTICAL_LABEL_NAMES
    from sim_service.dataset import VERTICAL_RANGES
    from sim_service.dataset import write_dataset as render_dataset

    vertical = render_dataset(tmp_path / "vertical", count=24, seed=5, progress=False, ranges=VERTICAL_RANGES)
    torch.manual_seed(0)
    vertical_model = tmp_path / "vertical.pt"
    model = CMVAE(labels=VERTICAL_LABEL_NAMES)
    torch.save(make_checkpoint(model, beta=8.0, epoch=1, val_loss=1.0, metrics={}), vertical_model)
    for checkpoint, expected in ((setup["checkpoint"], 3), (vertical_model, 4)):
        out = tmp_path / checkpoint.stem
        run(EvalEncoderSettings(checkpoint=str(checkpoint), dataset=str(vertical), out=str(out), batch_size=8))
        mae = json.loads((out / "metrics.json").read_text())["mae"]
        assert len(mae) == expected and ("elevation_deg" in mae) == (expected == 4)
    # a vertical model on planar frames: the three labels both have (is a 3d CMVAE as good where the dolphin is level?)
    out = tmp_path / "vertical-on-planar"
    run(EvalEncoderSettings(checkpoint=str(vertical_model), dataset=str(setup["clean"]), out=str(out), batch_size=8))
    assert set(json.loads((out / "metrics.json").read_text())["mae"]) == {"d_m", "theta_deg", "psi_deg"}


def test_labels_a_model_and_a_dataset_do_not_share_in_order_are_refused_naming_both() -> None:
    from types import SimpleNamespace

    from encoder_service.evaluate import shared_labels

    # No `swimm dataset` writes its labels in another order, so the datasets here are stand-ins with label names.
    planar = SimpleNamespace(root="data/planar", label_names=("d", "theta", "psi"))
    assert shared_labels(("d", "theta", "psi", "elevation"), planar) == ("d", "theta", "psi")
    swapped = SimpleNamespace(root="data/odd", label_names=("theta", "d", "psi"))
    with pytest.raises(ValueError, match="the model reads \\['d', 'theta', 'psi'\\] but data/odd labels"):
        shared_labels(("d", "theta", "psi"), swapped)
