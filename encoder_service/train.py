"""`swimm train-encoder`: fit the CMVAE on a dataset folder, with early stopping and resumable checkpoints.

The recipe is the reference's (SPEC "CMVAE"): Adam at 1e-4, batch 32, beta 8,
up to 100 epochs, stopping once the validation loss has failed to improve by
1% for 5 epochs. ``best.pt`` is the lowest validation loss seen; ``last.pt``
adds the optimiser and the early-stopping state so ``--resume`` picks up
exactly where a run stopped (the shuffle order is a function of (seed, epoch)).
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from tqdm import tqdm

from encoder_service import figures
from encoder_service.augment import AugmentSettings
from encoder_service.data import (
    AnyDataset,
    Batch,
    count_batches,
    iter_batches,
    open_datasets,
    prefetch,
    require_masks,
    split_indices,
)
from encoder_service.model import (
    CMVAE,
    EVALUATION_PRIORS_SEED,
    INPUT_NORMS,
    LABEL_NAMES,
    MIRROR_NEGATED,
    SPEC_STATE_LOSS,
    DistillationParts,
    LossParts,
    StateLoss,
    add_consistency_loss,
    check_state_loss,
    cmvae_loss,
    denormalise_labels,
    distillation_loss,
    encoder_input,
    images_to_tensor,
    input_channels,
    label_errors,
    load_model,
    make_checkpoint,
    mask_overlap,
    normalise_labels,
    pool_masks,
    read_checkpoint,
    resolve_device,
)
from services.geometry import ALPHA_DEG
from services.lifecycle import sigterm_as_ctrl_c
from services.results import provenance, refuse_held_folder, write_result
from services.settings import FilePath

log = logging.getLogger(__name__)


@dataclass
class TrainEncoderSettings(AugmentSettings):
    dataset: list[str] = field(default_factory=list)  # folders written by `swimm dataset`; several are read as one
    out: str = "runs/cmvae"
    epochs: int = 100
    batch_size: int = 32
    lr: float = 1e-4
    beta: float = 8.0
    n_z: int = 10
    patience: int = 5  # epochs without a min_rel_gain improvement before stopping
    min_rel_gain: float = 0.01
    val_fraction: float = 0.1
    seed: int = 0
    resume: bool = False  # continue from <out>/last.pt
    init: FilePath = ""  # start from this checkpoint's weights (fresh optimiser, epochs from 1): fine-tuning
    mirror: float = 0.5  # share of training frames flipped left-right (theta and psi change sign); 0 = off
    # training frames moved sideways by up to this many pixels, as if the camera had turned (theta and psi turn
    # with them): what a sub-pixel read near the image centre learns from; 0 = off
    shift_pixels: int = 0
    psi_loss: Literal["mse", "l1"] = "mse"  # mse: the SPEC's; l1: psi's absolute error, least at the likelier view
    theta_loss: Literal["mse", "l1"] = "mse"  # mse: the SPEC's; l1: theta's absolute error, which pulls near the centre
    clean_share: float = 0.5  # paired datasets: share of training frames fed clean, the rest noisy (targets are clean)
    teacher: FilePath = ""  # paired datasets: a CMVAE whose latent of each clean frame the model gives both twins
    latent_weight: float = 1.0  # with a teacher: weight of the latent match against the state error
    # with a teacher and augmentation: weight of the pull of each augmented frame's d and theta read toward the
    # model's own read of the frame unaugmented (0 = off)
    consistency_weight: float = 0.0
    # of d, theta, psi (and the elevation, for a --vertical dataset) in the state error
    state_weights: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    input_norm: str = "none"  # none | channel: white-balance | local: and even out the light | light: local + light
    mask_weight: float = 0.0  # > 0: a mask head learns where the dolphin is (needs `swimm dataset --masks`); 0 = none
    locate: bool = False  # the encoder reads where the dolphin is off a locator the masks train (needs --mask-weight)
    track: bool = False  # the encoder reads a prior, where the target was last seen, beside each frame: pods
    prior_distance: bool = False  # a tracking encoder's prior holds the target's last distance too (needs --track)
    mirror_average: bool = False  # the encoder averages each frame's reading with its mirror image's (symmetric)
    bn_batches: int = 50  # training batches that re-estimate batch-norm statistics before each validation; 0 = off
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    max_batches_per_epoch: int = 0  # cap on training batches per epoch; 0 = all (validation always runs in full)
    tensorboard: bool = True
    # also write each epoch's weights to <out>/epoch-N.pt: to read them one by one, or average them
    # (`swimm export-encoder --average`)
    keep_epochs: bool = False

    def state_loss(self) -> StateLoss:
        """The state error these settings ask for; a bad setting's error names its flag."""
        check_state_loss(self.psi_loss, "--psi-loss")
        check_state_loss(self.theta_loss, "--theta-loss")
        try:
            return StateLoss(psi=self.psi_loss, weights=tuple(self.state_weights), theta=self.theta_loss)
        except ValueError as error:
            raise ValueError(f"--state-weights: {error}") from None


@dataclass
class EarlyStopping:
    """Stop after ``patience`` epochs whose loss is not below ``reference * (1 - min_rel_gain)``.

    The reference moves only on such a gain, so a slow creep of tiny gains
    still runs out of patience.
    """

    patience: int
    min_rel_gain: float
    reference: float = math.inf
    epochs_without_gain: int = 0

    def update(self, loss: float) -> bool:
        """Record one epoch's loss; True when training should stop."""
        if loss < self.reference * (1.0 - self.min_rel_gain):
            self.reference = loss
            self.epochs_without_gain = 0
        else:
            self.epochs_without_gain += 1
        return self.epochs_without_gain >= self.patience


def _mean(totals: dict[str, float], count: int) -> dict[str, float]:
    return {key: value / max(count, 1) for key, value in totals.items()}


#: Label columns a left-right flip negates: theta and psi (d and, in vertical datasets, the elevation keep theirs).
MIRRORED_LABELS = [LABEL_NAMES.index(name) for name in MIRROR_NEGATED]


def mirror_batch(batch: Batch, flip: np.ndarray) -> Batch:
    """Flip the frames picked by ``flip`` left-right and negate their theta and psi.

    A mirrored frame is another true frame: the world reflected in the rover's vertical forward plane,
    where the target sits at -theta and faces -psi (the dolphin and the scene's lighting are
    left-right symmetric). It doubles what the encoder sees of each pose, and pairs every view of a
    dolphin facing left with one facing right, the cue z[2] has to find.
    """
    labels = batch.labels.copy()
    labels[np.ix_(flip, MIRRORED_LABELS)] *= -1.0  # a left-right flip leaves d and the elevation as they are
    return Batch(
        images=_mirrored(batch.images, flip),
        labels=labels,
        indices=batch.indices,
        clean=_mirrored(batch.clean, flip),
        masks=_mirrored(batch.masks, flip),
        centred=batch.centred,  # a mirror image keeps who is nearest the centre
    )


def _mirrored(frames: np.ndarray | None, flip: np.ndarray) -> np.ndarray | None:
    """A copy of ``frames`` (N, H, W, ...) with the rows picked by ``flip`` flipped left-right; None stays None."""
    if frames is None:
        return None
    frames = frames.copy()
    frames[flip] = frames[flip, :, ::-1]
    return frames


#: Label columns a sideways turn of the camera moves: the azimuth, and the target's heading against the rover's.
TURNED_LABELS = (LABEL_NAMES.index("theta"), LABEL_NAMES.index("psi"))
MAX_SHIFT_PIXELS = 16  # a quarter of the frame: beyond, an edge column would fill much of it


def shift_batch(batch: Batch, pixels: np.ndarray) -> Batch:
    """Move each frame ``pixels[i]`` columns to the right (left if negative), the edge column repeated, and turn
    its labels as a camera turned by that much would see them.

    A pinhole camera whose image moves right by s pixels has turned left: a target at azimuth theta (+ = left)
    lies at column -f tan(theta) from the centre, so it now reads atan(tan(theta) - s / f), f the focal length in
    pixels; its heading against the rover's (psi) turns by the same angle, and its distance and elevation keep
    theirs. Near the centre a pixel is 1.5 degrees, and the reading the log-shaped azimuth penalty rewards is a
    fraction of one: the shifts show the encoder each pose at other sub-pixel phases.
    """
    focal_px = focal_length_px(batch.images.shape[2])
    labels = batch.labels.copy()
    theta, psi = TURNED_LABELS
    moved = np.flatnonzero(pixels)  # the others keep their labels to the bit
    turned = np.degrees(np.arctan(np.tan(np.radians(labels[moved, theta])) - pixels[moved] / focal_px))
    labels[moved, psi] = (labels[moved, psi] + turned - labels[moved, theta] + 180.0) % 360.0 - 180.0
    labels[moved, theta] = turned
    return Batch(
        images=shifted_frames(batch.images, pixels),
        labels=labels,
        indices=batch.indices,
        clean=shifted_frames(batch.clean, pixels),
        masks=shifted_frames(batch.masks, pixels, fill_edge=False),
        centred=batch.centred,
    )


def focal_length_px(width: int) -> float:
    """The camera's horizontal focal length in pixels for frames ``width`` pixels wide."""
    return width / 2 / math.tan(math.radians(ALPHA_DEG))


def shifted_frames(frames: np.ndarray | None, pixels: np.ndarray, fill_edge: bool = True) -> np.ndarray | None:
    """A copy of ``frames`` (N, H, W, ...) with row i moved ``pixels[i]`` columns right; the columns it uncovers
    repeat the edge (``fill_edge``) or are zero (masks: no dolphin there). None stays None."""
    if frames is None:
        return None
    out = frames.copy()
    for row in np.flatnonzero(pixels):
        shift = int(pixels[row])
        uncovered = slice(0, shift) if shift > 0 else slice(shift, None)
        edge = frames[row][:, :1] if shift > 0 else frames[row][:, -1:]
        out[row] = np.roll(frames[row], shift, axis=1)
        out[row][:, uncovered] = edge if fill_edge else 0
    return out


def inputs_and_targets(batch: Batch, feed_clean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The frames the encoder reads and the frames the decoder must draw.

    A paired dataset's decoder target is always the clean frame, whichever frame went in: learning to draw the
    clean scene from a noisy view is what makes the latent ignore the noise (a denoising autoencoder). The
    rows picked by ``feed_clean`` go in clean, the rest noisy; an unpaired batch is its own target.
    """
    if batch.clean is None:
        return batch.images, batch.images
    if feed_clean is None:
        return batch.images, batch.clean
    return np.where(feed_clean[:, None, None, None], batch.clean, batch.images), batch.clean


def freeze_decoders(model: CMVAE) -> None:
    """Fix the image and state decoders' weights (their batch-norm statistics stay fixed in `_train_mode`), so the
    latent keeps the teacher's meaning."""
    for decoder in (model.image_decoder, model.state_decoders):
        decoder.requires_grad_(False)


def _train_mode(model: CMVAE) -> None:
    """Training mode for what trains; frozen decoders stay in eval mode so their batch-norm statistics hold."""
    model.train()
    for decoder in (model.image_decoder, model.state_decoders):
        if not any(parameter.requires_grad for parameter in decoder.parameters()):
            decoder.eval()


def _loss(
    model: CMVAE,
    batch: Batch,
    feed_clean: np.ndarray,
    settings: TrainEncoderSettings,
    device: torch.device,
    teacher: CMVAE | None,
    jitter_rng: np.random.Generator | None = None,
    priors: np.random.Generator | None = None,
) -> LossParts | DistillationParts:
    """The batch's loss parts: the CMVAE loss, or with a ``teacher`` the distillation loss; ``jitter_rng`` jitters
    a share of the inputs (never the targets); ``priors`` draws a tracking model's priors."""
    inputs, targets = inputs_and_targets(batch, feed_clean)
    plain_inputs = inputs
    if jitter_rng is not None:
        inputs = settings.augmented(inputs, jitter_rng)
    labels = torch.from_numpy(normalise_labels(batch.labels, model.labels)).to(device)
    images = encoder_input(model, inputs, batch.labels, device, priors, batch.centred)
    masks = _masks_tensor(batch, settings.mask_weight, device)
    mask_args = {"masks": masks, "mask_weight": settings.mask_weight}
    if teacher is None:
        targets_t = images_to_tensor(targets, device)
        return cmvae_loss(model(images), targets_t, labels, settings.beta, settings.state_loss(), **mask_args)
    with torch.no_grad():
        teacher_mu, teacher_logvar = teacher.encode(images_to_tensor(targets, device))
    parts = distillation_loss(
        model, images, teacher_mu, teacher_logvar, labels, settings.latent_weight, settings.state_loss(), **mask_args
    )
    if settings.consistency_weight > 0 and jitter_rng is not None:
        plain_images = encoder_input(model, plain_inputs, batch.labels, device, priors, batch.centred)
        parts = add_consistency_loss(parts, model, plain_images, settings.consistency_weight)
    return parts


def _masks_tensor(batch: Batch, mask_weight: float, device: torch.device) -> torch.Tensor | None:
    """The batch's masks on ``device`` when the mask head trains, else None (the masks are not read)."""
    return torch.from_numpy(batch.masks).to(device) if mask_weight > 0 else None


def _train_epoch(
    model: CMVAE,
    optimiser: torch.optim.Optimizer,
    dataset: AnyDataset,
    indices: np.ndarray,
    settings: TrainEncoderSettings,
    epoch: int,
    device: torch.device,
    teacher: CMVAE | None = None,
) -> dict[str, float]:
    _train_mode(model)
    totals: dict[str, float] = {}
    seen = 0
    batches = iter_batches(
        dataset, indices, settings.batch_size, (settings.seed, epoch), settings.max_batches_per_epoch
    )
    n_batches = count_batches(len(indices), settings.batch_size, settings.max_batches_per_epoch)
    flips = np.random.default_rng((settings.seed, epoch, 1))
    feeds = np.random.default_rng((settings.seed, epoch, 3))
    jitters = np.random.default_rng((settings.seed, epoch, 4))
    priors = np.random.default_rng((settings.seed, epoch, 5))
    shifts = np.random.default_rng((settings.seed, epoch, 6))
    with tqdm(
        prefetch(batches),
        total=n_batches,
        desc=f"epoch {epoch + 1}/{settings.epochs}",
        unit="batch",
        leave=False,
        dynamic_ncols=True,
    ) as bar:
        for batch in bar:
            if settings.mirror > 0:
                batch = mirror_batch(batch, flips.random(len(batch.indices)) < settings.mirror)
            if settings.shift_pixels > 0:
                span = settings.shift_pixels
                batch = shift_batch(batch, shifts.integers(-span, span + 1, len(batch.indices)))
            feed_clean = feeds.random(len(batch.indices)) < settings.clean_share
            loss = _loss(model, batch, feed_clean, settings, device, teacher, jitters, priors)
            optimiser.zero_grad(set_to_none=True)
            loss.total.backward()
            optimiser.step()
            parts = loss.as_floats()
            for key, value in parts.items():
                totals[key] = totals.get(key, 0.0) + value * len(batch.indices)
            seen += len(batch.indices)
            bar.set_postfix({key: f"{value:.4f}" for key, value in parts.items()})
    return _mean(totals, seen)


@torch.no_grad()
def recalibrate_batch_norm(
    model: CMVAE,
    dataset: AnyDataset,
    indices: np.ndarray,
    settings: TrainEncoderSettings,
    epoch: int,
    device: torch.device,
) -> None:
    """Re-estimate every batch-norm layer's running mean and variance at the model's final weights.

    Training keeps exponential averages of per-batch statistics over the last dozen or so batches, taken
    while the weights were still moving. With the SPEC's network at lr 3e-4 they lagged so far that eval mode
    scored d 0.56 m, theta 7.0 deg where the same weights with fresh statistics score 0.36 m and 1.4 deg. A
    cumulative average over ``bn_batches`` batches at fixed weights is what validation and the checkpoint
    then use.
    """
    _train_mode(model)
    layers = [module for module in model.modules() if isinstance(module, torch.nn.BatchNorm2d) and module.training]
    if not layers or settings.bn_batches <= 0:
        return
    momenta = [layer.momentum for layer in layers]
    for layer in layers:
        layer.reset_running_stats()
        layer.momentum = None  # a plain average over the batches below
    feeds = np.random.default_rng((settings.seed, epoch, 4))
    priors = np.random.default_rng((settings.seed, epoch, 6))
    for batch in iter_batches(dataset, indices, settings.batch_size, (settings.seed, epoch, 2), settings.bn_batches):
        inputs, _ = inputs_and_targets(batch, feeds.random(len(batch.indices)) < settings.clean_share)
        # eval decodes mu, so the decoder's layers see mu
        model(encoder_input(model, inputs, batch.labels, device, priors, batch.centred), sample=False)
    for layer, momentum in zip(layers, momenta, strict=True):
        layer.momentum = momentum


@torch.inference_mode()
def validate(
    model: CMVAE,
    dataset: AnyDataset,
    indices: np.ndarray,
    batch_size: int,
    beta: float,
    device: torch.device,
    state_loss: StateLoss = SPEC_STATE_LOSS,
    feed_clean: bool = False,
    teacher: CMVAE | None = None,
    latent_weight: float = 1.0,
    mask_weight: float = 0.0,
) -> dict[str, float]:
    """Mean losses on ``indices`` with z = mu, plus the MAE of each label in physical units.

    With ``mask_weight`` > 0 the mask loss joins the total and ``mask_iou`` is the predicted masks' intersection
    over union with the true ones (cells of the head's 8x8 grid, summed over all frames).

    A paired dataset is read noisy (its ``images``) unless ``feed_clean``; the decoder's target is its clean frame.
    With a ``teacher`` the losses are the distillation loss's (the latent match to the teacher's clean latent).
    """
    model.eval()
    totals: dict[str, float] = {}
    errors = np.zeros(len(model.labels))
    seen, overlap = 0, np.zeros(2)
    priors = np.random.default_rng(EVALUATION_PRIORS_SEED)  # every validation reads the same priors
    for batch in prefetch(iter_batches(dataset, indices, batch_size)):
        chosen = np.full(len(batch.indices), feed_clean)
        inputs, targets = inputs_and_targets(batch, chosen)
        labels = torch.from_numpy(normalise_labels(batch.labels, model.labels)).to(device)
        images = encoder_input(model, inputs, batch.labels, device, priors, batch.centred)
        targets_t = images_to_tensor(targets, device)
        masks = _masks_tensor(batch, mask_weight, device)
        mask_args = {"masks": masks, "mask_weight": mask_weight}
        if teacher is None:
            outputs = model(images)
            parts = cmvae_loss(outputs, targets_t, labels, beta, state_loss, **mask_args)
            state, mask_logits = outputs.state, outputs.mask
        else:
            teacher_mu, teacher_logvar = teacher.encode(targets_t)
            parts = distillation_loss(
                model, images, teacher_mu, teacher_logvar, labels, latent_weight, state_loss, **mask_args
            )
            state, mask_logits = parts.prediction, parts.mask_logits
        if masks is not None:
            overlap += mask_overlap(mask_logits, masks)
        for key, value in parts.as_floats().items():
            totals[key] = totals.get(key, 0.0) + value * len(batch.indices)
        predicted = denormalise_labels(state.float().cpu().numpy(), model.labels)
        errors += label_errors(predicted, batch.labels).sum(axis=0)
        seen += len(batch.indices)
    metrics = _mean(totals, seen)
    for name, error in zip(model.labels, errors, strict=True):
        metrics[f"mae_{name}"] = float(error / max(seen, 1))
    if mask_weight > 0:
        metrics["mask_iou"] = float(overlap[0] / max(overlap[1], 1.0))
    return metrics


def validate_all(
    model: CMVAE,
    dataset: AnyDataset,
    indices: np.ndarray,
    settings: TrainEncoderSettings,
    device: torch.device,
    teacher: CMVAE | None = None,
) -> dict[str, float]:
    """`validate`; on a paired dataset both noisy and clean inputs, ``total`` their mean and ``clean_*`` the latter's.

    Early stopping and ``best.pt`` then favour a model good on both, not one that gave up clean frames for noisy.
    """
    args = (model, dataset, indices, settings.batch_size, settings.beta, device, settings.state_loss())
    distill = {"teacher": teacher, "latent_weight": settings.latent_weight, "mask_weight": settings.mask_weight}
    metrics = validate(*args, **distill)
    if dataset.paired:
        clean = validate(*args, feed_clean=True, **distill)
        metrics |= {f"clean_{key}": value for key, value in clean.items()}
        metrics["total"] = (metrics["total"] + clean["total"]) / 2.0
    return metrics


@torch.inference_mode()
def save_mask_figure(model: CMVAE, dataset: AnyDataset, rows: np.ndarray, path: Path, device: torch.device) -> Path:
    """Frames (top), their true masks pooled to the head's grid (middle) and the head's predictions (bottom)."""
    model.eval()
    batch = dataset.read(rows)
    priors = np.random.default_rng(EVALUATION_PRIORS_SEED)
    images = encoder_input(model, batch.images, batch.labels, device, priors, batch.centred)
    predicted = torch.sigmoid(model(images).mask).cpu().numpy()
    true = pool_masks(torch.from_numpy(batch.masks), predicted.shape[-1]).numpy()
    overlays = [batch.images, figures.mask_overlay(batch.images, true), figures.mask_overlay(batch.images, predicted)]
    return figures.image_grid(
        [list(row) for row in overlays], path, "Where the dolphin is", row_labels=["frame", "true", "predicted"]
    )


def _save(checkpoint: dict[str, Any], path: Path) -> None:
    """Write then rename, so an interrupted save never leaves a half checkpoint behind."""
    partial = path.with_suffix(".tmp")
    torch.save(checkpoint, partial)
    os.replace(partial, path)


def load_init_weights(model: CMVAE, path: str, n_z: int) -> None:
    """Copy a checkpoint's weights (float32 or the shipped float16) into ``model``."""
    checkpoint = read_checkpoint(path)
    config = checkpoint["config"]
    if config["n_z"] != n_z:
        raise ValueError(f"--init {path} has n_z={config['n_z']}, settings say {n_z}")
    weights = {name: tensor.float() for name, tensor in checkpoint["state_dict"].items()}
    inherited_inputs = input_channels(
        config.get("input_norm", "none"), config.get("track", False), config.get("prior_distance", False)
    )
    model.load_state_dict(_matched_to(weights, model, inherited_inputs))
    log.info("starting from the weights of %s (its epoch %d)", path, checkpoint["epoch"])
    inherited = len(config.get("labels", LABEL_NAMES))
    for dim in range(inherited, len(model.labels)):
        revive_latent(model, dim)
        log.info("z[%d] restarts for the new label %r", dim, model.labels[dim])


#: The posterior spread a revived latent starts with: small, so its fresh decoder sees the encoder's signal.
REVIVED_STD = 0.1


def revive_latent(model: CMVAE, dim: int) -> None:
    """Restart z[dim]'s encoder output: a freshly drawn mean and a narrow posterior.

    A planar model leaves the unsupervised z[3] on the prior (mean ~0, spread 1); a new label's decoder reading
    it sees only sampling noise, learns to ignore it and sends no gradient back (docs/encoder.md, elevation).
    A fresh mean with a small spread gives the decoder a signal to follow.
    """
    last = model.encoder.head[-1]
    fresh = torch.nn.Linear(last.in_features, 1, device=last.weight.device)
    with torch.no_grad():
        last.weight[dim] = fresh.weight[0]
        last.bias[dim] = fresh.bias[0]
        last.weight[model.n_z + dim] = 0.0
        last.bias[model.n_z + dim] = 2.0 * math.log(REVIVED_STD)


#: Parts a CMVAE has or lacks by its settings: the mask head, the locator and the elevation label's state decoder.
OPTIONAL_PARTS = ("mask_head.", "encoder.locator.", f"state_decoders.{len(LABEL_NAMES)}.")


def _matched_to(
    weights: dict[str, torch.Tensor], model: CMVAE, inherited_inputs: tuple[str, ...]
) -> dict[str, torch.Tensor]:
    """``weights`` with the optional parts matched to ``model``'s: its fresh part where the checkpoint has none,
    the checkpoint's dropped where the model has none (the encoder is what carries over). A model that locates,
    tracks or reads the light, started from one that does not, reads the soft-argmax, the prior or the light
    through zero weights: it starts as the checkpoint. The first convolution's weights go to the input channels of
    the same name (``inherited_inputs``: the checkpoint's, :func:`input_channels`)."""
    own = model.state_dict()
    kept = {name: tensor for name, tensor in weights.items() if name in own or not name.startswith(OPTIONAL_PARTS)}
    fresh = {name: tensor for name, tensor in own.items() if name.startswith(OPTIONAL_PARTS) and name not in weights}
    # The head reads the locator's soft-argmax as two columns after the pooled features.
    head, wanted = kept["encoder.head.0.weight"], own["encoder.head.0.weight"].shape[1]
    widened = head.new_zeros(head.shape[0], wanted)
    widened[:, : min(wanted, head.shape[1])] = head[:, :wanted]
    kept["encoder.head.0.weight"] = widened
    first = kept["encoder.features.0.weight"]
    matched = first.new_zeros(own["encoder.features.0.weight"].shape)
    for channel, name in enumerate(model.encoder.input_channels):
        if name in inherited_inputs:
            matched[:, channel] = first[:, inherited_inputs.index(name)]
    kept["encoder.features.0.weight"] = matched
    return kept | fresh


def _teacher(settings: TrainEncoderSettings, dataset: AnyDataset, device: torch.device) -> CMVAE | None:
    """The frozen teacher of a distillation run, or None; refused unless every frame has its clean twin and the
    teacher's latent ties the dataset's labels (a planar teacher's z[3] is no elevation)."""
    if not settings.teacher:
        return None
    if not dataset.paired:
        raise ValueError(
            f"--teacher needs a paired dataset (each noisy frame with its clean twin, `swimm dataset --paired`); "
            f"{settings.dataset} is not paired"
        )
    teacher, checkpoint = load_model(settings.teacher, device)
    if teacher.labels != dataset.label_names:
        raise ValueError(
            f"--teacher {settings.teacher} reads {', '.join(teacher.labels)}; {settings.dataset}'s labels are "
            f"{', '.join(dataset.label_names)}: distil from a CMVAE of the same labels (a --vertical dataset from "
            "encoder_service/models/cmvae_vertical.pt)"
        )
    if teacher.n_z != settings.n_z:
        raise ValueError(f"--teacher {settings.teacher} has n_z={teacher.n_z}, settings say {settings.n_z}")
    log.info(
        "distilling from %s (its epoch %d): decoders frozen, latents matched", settings.teacher, checkpoint["epoch"]
    )
    return teacher.requires_grad_(False)


def _seed_everything(seed: int) -> None:
    np.random.seed(seed)
    torch.manual_seed(seed)


def check(settings: TrainEncoderSettings) -> None:
    """Refuse a training run's settings, datasets and folder before anything is trained or written."""
    if not settings.dataset:
        raise ValueError("no dataset given: pass --dataset DIR [DIR ...] (folders written by `swimm dataset`)")
    settings.state_loss()  # checked before the dataset is read, not at the first batch
    if settings.input_norm not in INPUT_NORMS:
        raise ValueError(f"--input-norm must be one of {', '.join(INPUT_NORMS)}, got {settings.input_norm!r}")
    settings.check_shares()
    if not 0 <= settings.shift_pixels <= MAX_SHIFT_PIXELS:
        raise ValueError(f"--shift-pixels must be 0 (off) to {MAX_SHIFT_PIXELS}, got {settings.shift_pixels}")
    if not (math.isfinite(settings.mask_weight) and settings.mask_weight >= 0):
        raise ValueError(f"--mask-weight must be a finite weight >= 0 (0 = no mask head), got {settings.mask_weight}")
    if settings.locate and settings.mask_weight <= 0:
        raise ValueError("--locate trains the locator on the dataset's masks: give it a --mask-weight > 0")
    if settings.prior_distance and not settings.track:
        raise ValueError("--prior-distance is a tracking encoder's prior: give --track too")
    if not (math.isfinite(settings.consistency_weight) and settings.consistency_weight >= 0):
        raise ValueError(f"--consistency-weight must be a weight >= 0 (0 = off), got {settings.consistency_weight}")
    if settings.consistency_weight > 0 and (not settings.teacher or settings.track):
        raise ValueError("--consistency-weight holds a distilled encoder's reads: give --teacher, and no --track")
    resolve_device(settings.device)
    if not settings.resume:
        refuse_held_folder("--out", settings.out, ("last.pt", "best.pt"), "a training run",
                           "--resume goes on with it; choose another --out for a new one")  # fmt: skip
    for flag, path in (("--init", settings.init), ("--teacher", settings.teacher)):
        if path:
            try:
                read_checkpoint(path)
            except (ValueError, FileNotFoundError) as exc:
                raise type(exc)(f"{flag} {exc}") from None
    open_datasets(settings.dataset)  # each folder a dataset this code reads


def run(settings: TrainEncoderSettings) -> int:
    check(settings)
    started = time.perf_counter()
    device = resolve_device(settings.device)
    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    _seed_everything(settings.seed)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True

    dataset = open_datasets(settings.dataset)
    if len(settings.state_weights) > len(dataset.label_names):
        labels = ", ".join(dataset.label_names)
        raise ValueError(f"--state-weights {settings.state_weights}: one weight per label, and {settings.dataset} "
                         f"labels {labels} (an elevation's weight needs a --vertical dataset)")  # fmt: skip
    if settings.mask_weight > 0:
        require_masks(dataset, "--mask-weight")
    train_rows, val_rows = split_indices(len(dataset), settings.val_fraction, settings.seed)
    if len(val_rows) == 0:
        raise ValueError("val_fraction is 0: early stopping and best.pt need a validation split")
    log.info(
        "dataset %s: %d rows (%d train, %d validation), device %s",
        settings.dataset,
        len(dataset),
        len(train_rows),
        len(val_rows),
        device,
    )

    mask_head = settings.mask_weight > 0 and not settings.locate  # a locator learns the masks itself
    model = CMVAE(
        settings.n_z, settings.input_norm, mask_head, dataset.label_names, settings.locate, settings.track,
        settings.mirror_average, settings.prior_distance,
    )  # fmt: skip
    model.to(device=device, memory_format=torch.channels_last)
    teacher = _teacher(settings, dataset, device)
    if teacher is not None:
        freeze_decoders(model)
    optimiser = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=settings.lr)
    stopper = EarlyStopping(settings.patience, settings.min_rel_gain)
    best_val, best_epoch, start_epoch = math.inf, 0, 0
    last_path, best_path = out / "last.pt", out / "best.pt"
    if settings.resume and last_path.is_file():
        last = read_checkpoint(last_path)
        if last["config"]["n_z"] != settings.n_z:
            raise ValueError(f"{last_path} has n_z={last['config']['n_z']}, settings say {settings.n_z}")
        if tuple(last["config"].get("labels", LABEL_NAMES)) != model.labels:
            raise ValueError(
                f"{last_path} learns labels {last['config'].get('labels')}, the dataset {list(model.labels)}"
            )
        for flag in ("locate", "track", "mirror_average", "prior_distance"):
            if last["config"].get(flag, False) != getattr(settings, flag):
                raise ValueError(f"{last_path} was trained with {flag}={last['config'].get(flag, False)}: resume it so")
        model.load_state_dict(last["state_dict"])
        optimiser.load_state_dict(last["optimizer"])
        torch.set_rng_state(last["torch_rng_state"])
        stopper = EarlyStopping(settings.patience, settings.min_rel_gain, **last["early_stopping"])
        best_val, best_epoch, start_epoch = last["best_val_loss"], last["best_epoch"], last["epoch"]
        log.info("resuming from %s after epoch %d (best validation loss %.5f)", last_path, start_epoch, best_val)
    elif settings.resume:
        log.warning("--resume given but %s does not exist; starting afresh", last_path)
    init = settings.init or settings.teacher  # a distilled encoder starts as its teacher, decoders and all
    if init and start_epoch == 0:
        load_init_weights(model, init, settings.n_z)

    writer = None
    if settings.tensorboard:
        from torch.utils.tensorboard import SummaryWriter  # imported late: tensorboard is slow to import

        writer = SummaryWriter(log_dir=str(out / "tb"))
    epochs_run, stopped_early, interrupted, metrics = 0, False, False, {}
    history: list[dict[str, float]] = []  # this invocation's epochs (a resumed run lists only its own)
    try:
        with sigterm_as_ctrl_c():
            for epoch in range(start_epoch, settings.epochs):
                train_metrics = _train_epoch(model, optimiser, dataset, train_rows, settings, epoch, device, teacher)
                recalibrate_batch_norm(model, dataset, train_rows, settings, epoch, device)
                metrics = validate_all(model, dataset, val_rows, settings, device, teacher)
                epochs_run += 1
                val_loss = metrics["total"]
                entry = {"epoch": epoch + 1, "train_loss": train_metrics["total"], "val_loss": val_loss}
                if "mask" in metrics:
                    entry |= {"train_mask": train_metrics["mask"], "val_mask": metrics["mask"]}
                    entry["val_mask_iou"] = metrics["mask_iou"]
                history.append(entry)
                if writer is not None:
                    for key, value in train_metrics.items():
                        writer.add_scalar(f"train/{key}", value, epoch + 1)
                    for key, value in metrics.items():
                        writer.add_scalar(f"val/{key}", value, epoch + 1)
                    writer.flush()
                log.info(
                    "epoch %d: train %.5f, validation %.5f (MAE d %.3f m, theta %.2f deg, psi %.1f deg%s)%s",
                    epoch + 1,
                    train_metrics["total"],
                    val_loss,
                    metrics["mae_d"],
                    metrics["mae_theta"],
                    metrics["mae_psi"],
                    f", elevation {metrics['mae_elevation']:.2f} deg" if "mae_elevation" in metrics else "",
                    f", mask loss {metrics['mask']:.4f}, IoU {metrics['mask_iou']:.3f}" if "mask" in metrics else "",
                )
                weights = make_checkpoint(model, settings.beta, epoch + 1, val_loss, metrics)
                if val_loss < best_val:
                    best_val, best_epoch = val_loss, epoch + 1
                    _save(weights, best_path)
                if settings.keep_epochs:
                    _save(weights, out / f"epoch-{epoch + 1}.pt")
                stop = stopper.update(val_loss)
                _save(
                    make_checkpoint(
                        model,
                        settings.beta,
                        epoch + 1,
                        val_loss,
                        metrics,
                        optimizer=optimiser.state_dict(),
                        torch_rng_state=torch.get_rng_state(),
                        seed=settings.seed,
                        best_val_loss=best_val,
                        best_epoch=best_epoch,
                        early_stopping={
                            "reference": stopper.reference,
                            "epochs_without_gain": stopper.epochs_without_gain,
                        },
                    ),
                    last_path,
                )
                if stop:
                    stopped_early = True
                    log.info(
                        "early stop after epoch %d: no %.1f%% gain for %d epochs",
                        epoch + 1,
                        100 * settings.min_rel_gain,
                        settings.patience,
                    )
                    break
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: best.pt and last.pt hold the finished epochs; say so, summarise
        interrupted = True
        log.warning("interrupted during epoch %d; --resume goes on from %s", start_epoch + epochs_run + 1, last_path)
    finally:
        if writer is not None:
            writer.close()

    summary = {
        "settings": asdict(settings),
        "device": str(device),
        "dataset_count": len(dataset),
        "train_count": len(train_rows),
        "val_count": len(val_rows),
        "start_epoch": start_epoch + 1,  # epochs count from 1, as in checkpoints and logs
        "epochs_run": epochs_run,
        "last_epoch": start_epoch + epochs_run,
        "stopped_early": stopped_early,
        "interrupted": interrupted,
        "best_epoch": best_epoch,
        "best_val_loss": best_val,
        "last_val_metrics": metrics,
        "history": history,
        "wall_time_s": time.perf_counter() - started,
    }
    starts = {"init": settings.init, "teacher": settings.teacher}
    write_result(out / "train_summary.json", summary, provenance(starts, seeds=[settings.seed]))
    if settings.mask_weight > 0 and epochs_run > 0:
        save_mask_figure(model, dataset, val_rows[:8], out / "masks.png", device)
    log.info("done: best validation loss %.5f at epoch %d; %s", best_val, best_epoch, best_path)
    return 130 if interrupted else 0
