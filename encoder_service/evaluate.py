"""`swimm eval-encoder`: how well a CMVAE reads state from frames, and how its latents move under noise.

Numbers (metrics.json) are those of the paper's encoder tables: the MAE of d,
theta and psi in physical units and divided by each label's range, and the
pixel MAE of reconstructions in 0-255. Given a second dataset rendered from
the same seed with noise on, it also reports the MAE on the noisy frames and
the mean drift of z[0..2] between the clean and noisy encodings of each pose
(the paper's Tables 14 and 15). Figures show reconstructions, an
interpolation between a near and a far target, and what each latent
dimension does when swept alone.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from encoder_service import figures
from encoder_service.data import CMVAEDataset, count_batches, iter_batches, prefetch
from encoder_service.inference import DEFAULT_CHECKPOINT
from encoder_service.model import (
    CMVAE,
    EVALUATION_PRIORS_SEED,
    LABEL_NAMES,
    denormalise_labels,
    encoder_input,
    label_errors,
    label_ranges,
    load_model,
    read_checkpoint,
    resolve_device,
    tensor_to_images,
)
from services.geometry import camera_centred
from services.results import provenance, write_result
from services.settings import FilePath

log = logging.getLogger(__name__)

UNIT_SUFFIX = {"d": "d_m", "theta": "theta_deg", "psi": "psi_deg", "elevation": "elevation_deg"}
N_SHOWN = 8  # frames per reconstruction figure
SWEEP = np.linspace(-3.0, 3.0, 9)  # the prior's +-3 sigma, for the per-dimension sweeps


@dataclass
class EvalEncoderSettings:
    checkpoint: FilePath = ""  # default: the shipped model, encoder_service/models/cmvae.pt
    dataset: str = ""  # held-out frames written by `swimm dataset` (a seed the encoder was not trained on)
    out: str = "runs/cmvae-eval"
    noisy_dataset: str = ""  # optional: the same seed rendered with noise on
    batch_size: int = 256
    max_images: int = 0  # 0 = the whole dataset
    device: str = "auto"


@dataclass
class EncodedSet:
    """One pass of the model over some rows: latents, decoded states and reconstruction errors."""

    mu: np.ndarray  # (N, n_z)
    predicted: np.ndarray  # (N, labels) physical units
    labels: np.ndarray  # (N, labels) physical units
    image_mae: float  # mean |reconstruction - input| in 0-255
    image_mae_vs_reference: float | None  # the same against the reference dataset's frames, when one is given
    names: tuple[str, ...] = LABEL_NAMES  # the labels read: those the model and the dataset share


@torch.inference_mode()
def encode_rows(
    model: CMVAE,
    dataset: CMVAEDataset,
    rows: np.ndarray,
    batch_size: int,
    device: torch.device,
    reference: CMVAEDataset | None = None,
    desc: str = "encoding",
) -> EncodedSet:
    """Run ``model`` (z = mu) over ``rows``; ``reference`` (same poses) adds the reconstruction error against it.

    The labels read are those the model and the dataset share (:func:`shared_labels`)."""
    names = shared_labels(model.labels, dataset)
    mus, predictions, labels = [], [], []
    abs_error, abs_error_reference, pixels = 0.0, 0.0, 0
    batches = prefetch(iter_batches(dataset, rows, batch_size))
    priors = np.random.default_rng(EVALUATION_PRIORS_SEED)  # a tracking model's, about the true azimuths
    for batch in tqdm(batches, total=count_batches(len(rows), batch_size), desc=desc, unit="batch", leave=False):
        outputs = model(encoder_input(model, batch.images, batch.labels, device, priors, batch.centred), sample=False)
        reconstructions = tensor_to_images(outputs.image).astype(np.int16)
        abs_error += float(np.abs(reconstructions - batch.images).sum())
        pixels += batch.images.size
        if reference is not None:
            twin = reference.read(batch.indices)
            abs_error_reference += float(np.abs(reconstructions - twin.images).sum())
        mus.append(outputs.mu.float().cpu().numpy())
        predictions.append(denormalise_labels(outputs.state[:, : len(names)].float().cpu().numpy(), names))
        labels.append(batch.labels[:, : len(names)])
    return EncodedSet(
        mu=np.concatenate(mus),
        predicted=np.concatenate(predictions),
        labels=np.concatenate(labels),
        image_mae=abs_error / pixels,
        image_mae_vs_reference=abs_error_reference / pixels if reference is not None else None,
        names=names,
    )


def shared_labels(model_labels: tuple[str, ...], dataset: CMVAEDataset) -> tuple[str, ...]:
    """The labels both read, in order: a planar model reads a vertical dataset's d, theta and psi, and a vertical
    model a planar dataset's (the elevation left out); any other difference is refused, naming both."""
    count = min(len(model_labels), len(dataset.label_names))
    if tuple(dataset.label_names[:count]) != tuple(model_labels[:count]):
        raise ValueError(f"the model reads {list(model_labels)} but {dataset.root} labels {list(dataset.label_names)}")
    return tuple(model_labels[:count])


def require_same_poses(clean: CMVAEDataset, noisy: CMVAEDataset, rows: np.ndarray) -> None:
    """Refuse a noisy dataset that does not show the clean one's poses row for row (drift would be meaningless)."""
    if len(noisy) < len(rows):
        raise ValueError(f"noisy dataset {noisy.root} holds {len(noisy)} rows, fewer than the {len(rows)} evaluated")
    differs = np.flatnonzero(~np.isclose(clean.read_labels(rows), noisy.read_labels(rows), atol=1e-4).all(axis=1))
    if differs.size:
        raise ValueError(
            f"{clean.root} and {noisy.root} do not show the same poses (first difference at row "
            f"{int(rows[differs[0]])}); render both with the same seed"
        )


def state_metrics(encoded: EncodedSet) -> dict[str, Any]:
    """MAE per label in physical units (psi wrapped) and divided by the label's range, as the paper reports.

    Also the MAE per distance band: fog and depth of field hide a far dolphin more than a near one, and the
    tracking band (4 to 8 m) is where a policy reads the encoder.
    """
    errors = label_errors(encoded.predicted, encoded.labels)
    mae = errors.mean(axis=0)
    low, high = label_ranges(encoded.names).T
    widths = high - low

    def named(values: np.ndarray) -> dict[str, float]:
        return {UNIT_SUFFIX[name]: float(value) for name, value in zip(encoded.names, values, strict=True)}

    distance = encoded.labels[:, 0]
    by_distance = {}
    for low, high in DISTANCE_BANDS_M:
        inside = (distance >= low) & (distance < high)
        if inside.any():
            by_distance[f"{low:g}-{high:.0f}m"] = named(errors[inside].mean(axis=0))
    return {
        "mae": named(mae),
        "mae_normalised": {name: float(value) for name, value in zip(encoded.names, mae / widths, strict=True)},
        "mae_by_distance": by_distance,
    }


def camera_label_check(encoded: EncodedSet, poses: np.ndarray) -> dict[str, float]:
    """Would labels measured from the camera (0.235 m ahead of the rover's centre) suit the encoder better?

    The SPEC measures d and theta from the rover's centre; the camera sees from its nose. If the encoder's azimuth
    errors followed the gap between the two, part of its error would be the labels' and camera-centred labels
    would remove it: ``theta_error_share_of_gap`` is that part (R^2 of the signed error on the gap). Also the
    azimuth MAE against camera-centred labels, and the gap itself.
    """
    _, camera_azimuth = camera_centred(poses[:, 0:2], poses[:, 5], poses[:, 6:8])
    rover_azimuth = encoded.labels[:, 1]
    gap = (camera_azimuth - rover_azimuth + 180.0) % 360.0 - 180.0  # both near 0 in practice; wrapped anyway
    error = encoded.predicted[:, 1] - rover_azimuth
    share = float(np.corrcoef(error, gap)[0, 1] ** 2) if gap.std() > 0 and error.std() > 0 else 0.0
    return {
        "theta_mae_rover_deg": float(np.abs(error).mean()),
        "theta_mae_camera_deg": float(np.abs(encoded.predicted[:, 1] - camera_azimuth).mean()),
        "gap_mean_abs_deg": float(np.abs(gap).mean()),
        "gap_max_abs_deg": float(np.abs(gap).max()),
        "theta_error_share_of_gap": share,
    }


PSI_VIEWS = {  # |psi| bands (deg): how much of the dolphin's outline tells which way it faces
    "head_on": (0.0, 30.0),
    "oblique_front": (30.0, 60.0),
    "side": (60.0, 120.0),
    "oblique_back": (120.0, 150.0),
    "from_behind": (150.0, 180.01),
}
DISTANCE_BANDS_M = ((2.0, 4.0), (4.0, 6.0), (6.0, 8.0), (8.0, 10.01))
REVERSED_DEG = 135.0  # a psi error beyond this reads the dolphin the wrong way round


def psi_breakdown(encoded: EncodedSet) -> dict[str, Any]:
    """Where psi's error comes from: its median, the share read the wrong way round, and its MAE by view and distance.

    The mean alone hides that most frames are read to within a few tens of degrees while head-on and
    far views, a few pixels of flukes against a rostrum, are sometimes read facing the other way.
    """
    errors = label_errors(encoded.predicted, encoded.labels)[:, 2]
    true_psi, distance = np.abs(encoded.labels[:, 2]), encoded.labels[:, 0]

    def band_mae(values: np.ndarray, low: float, high: float) -> float | None:
        inside = (values >= low) & (values < high)
        return float(errors[inside].mean()) if inside.any() else None

    return {
        "median_deg": float(np.median(errors)),
        "reversed_share": float((errors > REVERSED_DEG).mean()),
        "mae_by_view_deg": {view: band_mae(true_psi, *edges) for view, edges in PSI_VIEWS.items()},
        "mae_by_distance_deg": {
            f"{low:g}-{high:.0f}m": band_mae(distance, low, high) for low, high in DISTANCE_BANDS_M
        },
    }


@torch.inference_mode()
def _decode(model: CMVAE, z: np.ndarray, device: torch.device) -> np.ndarray:
    return tensor_to_images(model.decode_image(torch.from_numpy(z.astype(np.float32)).to(device)))


def _write_figures(
    model: CMVAE, dataset: CMVAEDataset, rows: np.ndarray, encoded: EncodedSet, out: Path, device: torch.device
) -> list[str]:
    shown = rows[:N_SHOWN]
    originals = dataset.read(shown).images
    paths = [
        figures.image_grid(
            [list(originals), list(_decode(model, encoded.mu[: len(shown)], device))],
            out / "reconstructions.png",
            "Frames (top) and their reconstructions from mu (bottom)",
            row_labels=["input", "decoded"],
        )
    ]
    near, far = int(np.argmin(encoded.labels[:, 0])), int(np.argmax(encoded.labels[:, 0]))
    weights = np.linspace(0.0, 1.0, 8)[:, None]
    path_z = (1 - weights) * encoded.mu[near] + weights * encoded.mu[far]
    paths.append(
        figures.image_grid(
            [list(dataset.read(rows[[near, far]]).images), list(_decode(model, path_z, device))],
            out / "interpolation.png",
            f"Latent interpolation: d = {encoded.labels[near, 0]:.1f} m to {encoded.labels[far, 0]:.1f} m",
            row_labels=["endpoints", "decoded"],
        )
    )
    base = encoded.mu.mean(axis=0)
    sweeps = []
    for dim in range(model.n_z):
        z = np.repeat(base[None], len(SWEEP), axis=0)
        z[:, dim] = SWEEP
        sweeps.append(list(_decode(model, z, device)))
    paths.append(
        figures.image_grid(
            sweeps,
            out / "latent_sweeps.png",
            "Each latent swept alone over the prior's +-3 sigma (others at their mean)",
            row_labels=[f"z[{dim}]" for dim in range(model.n_z)],
            col_labels=[f"{value:+.1f}" for value in SWEEP],
        )
    )
    paths.append(figures.state_scatter(encoded.predicted, encoded.labels, encoded.names, out / "state_scatter.png"))
    return [str(path) for path in paths]


def _noise_report(
    model: CMVAE,
    clean: CMVAEDataset,
    noisy: CMVAEDataset,
    rows: np.ndarray,
    clean_set: EncodedSet,
    settings: EvalEncoderSettings,
    out: Path,
    device: torch.device,
) -> tuple[dict[str, Any], list[str]]:
    noisy_set = encode_rows(model, noisy, rows, settings.batch_size, device, reference=clean, desc="noisy")
    drift = np.abs(clean_set.mu - noisy_set.mu).mean(axis=0)
    report = {
        "dataset": str(noisy.root),
        **state_metrics(noisy_set),
        "image_mae_255": noisy_set.image_mae,
        "image_mae_255_vs_clean": noisy_set.image_mae_vs_reference,
        "latent_drift": {f"z{dim}": float(drift[dim]) for dim in range(len(model.labels))},
        "latent_drift_all": [float(value) for value in drift],
    }
    shown = rows[:N_SHOWN]
    grid = [
        list(clean.read(shown).images),
        list(noisy.read(shown).images),
        list(_decode(model, clean_set.mu[: len(shown)], device)),
        list(_decode(model, noisy_set.mu[: len(shown)], device)),
    ]
    paths = [
        figures.image_grid(
            grid,
            out / "noise_comparison.png",
            "Clean and noisy frames of the same poses",
            row_labels=["clean", "noisy", "decoded clean", "decoded noisy"],
        ),
        figures.drift_bars(drift, out / "latent_drift.png"),
    ]
    return report, [str(path) for path in paths]


def check(settings: EvalEncoderSettings) -> None:
    """Refuse the settings, the model and the datasets before anything is read in full or written."""
    if not settings.dataset:
        raise ValueError("no dataset given: pass --dataset DIR (held-out frames from `swimm dataset`)")
    resolve_device(settings.device)
    config = read_checkpoint(settings.checkpoint or DEFAULT_CHECKPOINT)["config"]
    for root in filter(None, (settings.dataset, settings.noisy_dataset)):
        shared_labels(tuple(config.get("labels", LABEL_NAMES)), CMVAEDataset(root))  # a folder this code reads


def run(settings: EvalEncoderSettings) -> int:
    check(settings)
    device = resolve_device(settings.device)
    checkpoint = Path(settings.checkpoint) if settings.checkpoint else DEFAULT_CHECKPOINT
    model, checkpoint_dict = load_model(checkpoint, device)
    dataset = CMVAEDataset(settings.dataset)
    count = min(len(dataset), settings.max_images) if settings.max_images > 0 else len(dataset)
    rows = np.arange(count)
    noisy = CMVAEDataset(settings.noisy_dataset) if settings.noisy_dataset else None
    if noisy is not None:
        require_same_poses(dataset, noisy, rows)
    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    log.info("evaluating %s on %d frames of %s (%s)", checkpoint, count, dataset.root, device)

    encoded = encode_rows(model, dataset, rows, settings.batch_size, device)
    metrics: dict[str, Any] = {
        "checkpoint": str(checkpoint),
        "checkpoint_epoch": int(checkpoint_dict["epoch"]),
        "dataset": str(dataset.root),
        "dataset_seed": dataset.seed,
        "count": count,
        "n_z": model.n_z,
        **state_metrics(encoded),
        "psi": psi_breakdown(encoded),
        "camera_labels": camera_label_check(encoded, dataset.read_poses(rows)),
        "image_mae_255": encoded.image_mae,
        "latent_std": [float(value) for value in encoded.mu.std(axis=0)],
        "settings": asdict(settings),
    }
    written = _write_figures(model, dataset, rows, encoded, out, device)
    if noisy is not None:
        metrics["noisy"], noisy_figures = _noise_report(model, dataset, noisy, rows, encoded, settings, out, device)
        written += noisy_figures
    metrics["figures"] = written
    write_result(out / "metrics.json", metrics, provenance({"encoder": checkpoint}, seeds=[dataset.seed]))
    mae = metrics["mae"]
    log.info(
        "MAE d %.3f m, theta %.2f deg, psi %.1f deg (median %.1f); image MAE %.1f/255; wrote %s",
        mae["d_m"],
        mae["theta_deg"],
        mae["psi_deg"],
        metrics["psi"]["median_deg"],
        encoded.image_mae,
        out / "metrics.json",
    )
    return 0
