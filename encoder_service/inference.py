"""Frames in, latents out: the CMVAE's encoder half, wrapped for the encoder service and for in-process use.

Only the image encoder runs per frame (the decoders are for training and
figures), in eval mode under ``torch.inference_mode`` with channels_last
input. ``decode_state`` turns latents back into (d, theta, psi[, elevation]) for
diagnostics, the eval views and the camera-only tracker.

The torch engine runs a frozen TorchScript trace: at batch 1 the encoder's time is mostly Python dispatch
between its small layers, which tracing removes (docs/benchmarks.md, the encoder's frozen trace). torch marks
``jit.trace`` deprecated; should tracing fail or disappear, the encoder falls back to eager mode with a logged
warning and stays correct, only slower.

``engine="onnx"`` runs the same encoder under onnxruntime instead (exported in memory at load, CPU only): faster
(docs/benchmarks.md), latents within 1e-4 of torch's (tested), and batch-invariant (a frame's latent is bit for
bit the same alone or in any batch, which the trace's is not).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoder_service import DEFAULT_CHECKPOINT, ENGINES
from encoder_service.model import (
    CMVAE,
    PriorReader,
    check_images,
    denormalise_labels,
    images_to_tensor,
    load_model,
    read_checkpoint,
)
from encoder_service.onnx_engine import onnx_runtime
from encoder_service.pod_encoder import PodEncoder, is_detector
from services.messages import IMAGE_SHAPE

log = logging.getLogger(__name__)

#: (frames, priors) -> (mu, logvar), and a tracking model's next priors (:class:`PriorReader`) after them; a model
#: that does not track is run on the frames alone.
Encoder = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]


def _inputs(model: CMVAE, device: torch.device | str) -> tuple[torch.nn.Module, tuple[torch.Tensor, ...], list[str]]:
    """The module an engine runs for ``model``'s encoder, an example input and the inputs' names: a tracking
    encoder reads each frame's prior too, and gives the next (:class:`PriorReader`)."""
    example = images_to_tensor(np.zeros((1, *IMAGE_SHAPE), dtype=np.uint8), device)
    if model.tracks:
        return PriorReader(model), (example, torch.zeros(1, *model.prior_shape, device=device)), ["images", "prior"]
    return model.encoder, (example,), ["images"]


def _traced_or_eager(model: CMVAE, device: torch.device) -> Encoder:
    """A frozen TorchScript trace of the (eval-mode) encoder, or the module itself if tracing fails."""
    encoder, example, _ = _inputs(model, device)
    try:
        with warnings.catch_warnings(), torch.inference_mode():
            warnings.simplefilter("ignore", FutureWarning)  # the deprecation notice, see the module docstring
            return _as_encoder(torch.jit.freeze(torch.jit.trace(encoder, example).eval()), model.tracks)
    except Exception as exc:  # any tracing failure leaves a correct, slower path
        log.warning("TorchScript tracing of the encoder failed (%s); using eager mode", exc)
        return _as_encoder(encoder, model.tracks)


def _as_encoder(module: Callable[..., Any], tracks: bool) -> Encoder:
    """``module`` as an :data:`Encoder`: one that does not track is called on the frames alone."""
    return module if tracks else lambda images, prior: module(images)


def _onnx_runtime(model: CMVAE, threads: int | None) -> Encoder:
    """The encoder exported to ONNX in memory and run by onnxruntime on ``threads`` CPU threads (default 1)."""
    encoder, example, names = _inputs(model.cpu(), "cpu")
    outputs = ["mu", "logvar", "next_prior"] if model.tracks else ["mu", "logvar"]
    return _as_encoder(onnx_runtime(encoder, example, names, outputs, threads), model.tracks)


def check_engine(engine: str, device: str) -> None:
    """Refuse an engine this code has not, or one that cannot run on ``device``."""
    if engine not in ENGINES or (engine == "onnx" and device != "cpu"):
        raise ValueError(f"encoder engine must be one of {', '.join(ENGINES)} (onnx on the cpu device only), "
                         f"got {engine!r} on {device!r}")  # fmt: skip


class LatentEncoder:
    """Loads a CMVAE checkpoint and encodes uint8 frames (N, 64, 64, 3) into (mu, logvar), each (N, n_z) float32."""

    def __init__(
        self,
        checkpoint: str | Path = DEFAULT_CHECKPOINT,
        device: str = "cpu",
        threads: int | None = None,
        engine: str = "torch",
    ) -> None:
        check_engine(engine, device)
        path = Path(checkpoint)
        if not path.is_file():
            raise FileNotFoundError(
                f"CMVAE checkpoint {path} does not exist; make one with `swimm train-encoder --dataset DIR` "
                f"(datasets come from `swimm dataset`) and pass its best.pt"
            )
        if threads is not None:
            torch.set_num_threads(threads)  # process-wide: an encoder process owns its cores
        self.device = torch.device(device)
        self._model, checkpoint_dict = load_model(path, self.device)
        if engine == "onnx":
            self._encoder = _onnx_runtime(self._model, threads)
        else:
            self._encoder = _traced_or_eager(self._model, self.device)
        self.engine = engine
        self.n_z = self._model.n_z
        self.checkpoint = path
        self.trained_epochs = int(checkpoint_dict["epoch"])
        log.info("CMVAE %s loaded (n_z=%d, %d epochs) on %s, %s engine", path, self.n_z, self.trained_epochs,
                 self.device, engine)  # fmt: skip

    def encode(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(mu, logvar) for a batch of RGB frames; a tracking model reads each frame's prior (N,), the azimuth in
        degrees where its target was last seen (:meth:`track` gives the next), the image centre where None (the
        engagement rule: the target is the dolphin the camera is centred on). A model that does not track ignores
        them."""
        mu, logvar, *_ = self._run(images, priors)
        return mu, logvar

    def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A tracking model's (mu, logvar) as :meth:`encode` gives them, and each env's next prior (N,) degrees: the
        azimuth its latent decodes to (:class:`encoder_service.model.PriorReader`)."""
        if not self.tracks:
            raise ValueError(f"CMVAE {self.checkpoint} does not track (no prior to hand on): call encode()")
        mu, logvar, next_priors = self._run(images, priors)
        return mu, logvar, next_priors

    @torch.inference_mode()
    def _run(self, images: np.ndarray, priors: np.ndarray | None) -> tuple[np.ndarray, ...]:
        check_images(images)
        shape = (len(images), *self._model.prior_shape)
        if priors is None:
            priors = np.zeros(shape, dtype=np.float32)
        priors = np.asarray(priors, dtype=np.float32)
        if priors.shape != shape or not np.isfinite(priors).all():
            what = " and distances in metres" if self._model.prior_distance else ""
            raise ValueError(f"priors must be {len(images)} finite azimuths in degrees{what}, one per frame, shaped "
                             f"{shape}, got {priors!r}")  # fmt: skip
        prior = torch.from_numpy(priors).to(self.device)
        outputs = self._encoder(images_to_tensor(images, self.device), prior)
        return tuple(output.float().cpu().numpy() for output in outputs)

    @property
    def tracks(self) -> bool:
        """Whether the model reads a prior beside each frame (trained with ``swimm train-encoder --track``)."""
        return self._model.tracks

    @property
    def prior_shape(self) -> tuple[int, ...]:
        """One frame's prior: () for an azimuth, (2,) for an azimuth and a distance (``--prior-distance``)."""
        return self._model.prior_shape

    @property
    def labels(self) -> tuple[str, ...]:
        """What the state decoders read: (d, theta, psi), and the elevation for a model trained on vertical frames."""
        return self._model.labels

    @torch.inference_mode()
    def decode_state(self, mu: np.ndarray) -> tuple[np.ndarray, ...]:
        """One array (N,) per label from latents (N, n_z): d metres, theta degrees (signed azimuth), psi degrees,
        and for a vertical model the elevation in degrees (+ = above)."""
        mu = np.asarray(mu, dtype=np.float32)
        if mu.ndim != 2 or mu.shape[1] != self.n_z:
            raise ValueError(f"latents must be shaped (N, {self.n_z}), got {mu.shape}")
        normalised = self._model.decode_state(torch.from_numpy(mu).to(self.device)).float().cpu().numpy()
        physical = denormalise_labels(normalised, self._model.labels)
        return tuple(physical.T)


def open_encoder(
    checkpoint: str | Path = DEFAULT_CHECKPOINT, device: str = "cpu", threads: int | None = None, engine: str = "torch"
) -> LatentEncoder | PodEncoder:
    """The encoder a checkpoint holds: a CMVAE's :class:`LatentEncoder`, or for a pod detector's checkpoint its
    detector and tracker (encoder_service.pod_encoder), which run on the cpu only."""
    if is_detector(checkpoint):
        refuse_detector_engine(checkpoint, engine, device)
        return PodEncoder(checkpoint, threads=threads, engine=engine)
    return LatentEncoder(checkpoint, device, threads, engine)


def refuse_detector_engine(detector: str | Path, engine: str, device: str) -> None:
    """A pod detector runs on the cpu only so far, under either engine: refuse another device (or an engine this
    code has not) by name."""
    if engine not in ENGINES or device != "cpu":
        raise ValueError(f"{detector} is a pod detector, which runs on the cpu only so far (engine "
                         f"{' or '.join(ENGINES)}); got engine {engine!r} on device {device!r}")  # fmt: skip


def check_encoder_file(checkpoint: str | Path, engine: str, device: str) -> None:
    """What :func:`open_encoder` would refuse, without building the model: a file that is neither a CMVAE nor a pod
    detector (named), or a detector on an engine it has not."""
    if is_detector(checkpoint):
        refuse_detector_engine(checkpoint, engine, device)
    else:
        read_checkpoint(checkpoint)
