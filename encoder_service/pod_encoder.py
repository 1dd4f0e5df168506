"""The pod detector and tracker as an encoder: frames and the loop's tracker state in, the target's latent out.

It answers as a tracking CMVAE does (``track(images, priors) -> (mu, logvar, next priors)``), its prior the
tracker's whole state (services.pod_tracker), so the loops that carry a tracking CMVAE's prior carry it and
keep the encoder stateless. The latent holds the target's distance and azimuth where a CMVAE's state decoders read
them (normalised as the labels are; target yaw and the rest 0), so the camera-only scripted tracker flies on it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoder_service import DETECTOR_FORMAT, ENGINES
from encoder_service.model import LABEL_NAMES, check_images, denormalise_labels, images_to_tensor, normalise_labels
from encoder_service.onnx_engine import onnx_runtime
from encoder_service.pod_detector import PodDetector, decode
from services.detections import Detections
from services.messages import IMAGE_SHAPE
from services.pod_tracker import STATE_SIZE, UNSEEN, PodTracker

log = logging.getLogger(__name__)

DETECTOR_VERSION = 1
N_Z = 10  # a CMVAE's latent size, so the same policies' observation fits


def _load(path: str | Path) -> Any:
    """The object a torch file holds, or None for a file torch cannot read (the CMVAE loader names what is wrong)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # torch has no one error for a file not its own
        return None


def is_detector(path: str | Path) -> bool:
    """Whether ``path`` is a pod detector checkpoint (rather than a CMVAE's)."""
    saved = _load(path)
    return isinstance(saved, dict) and saved.get("format") == DETECTOR_FORMAT


def read_detector(path: str | Path, what: str = "the checkpoint") -> dict[str, Any]:
    """A pod detector checkpoint's contents, read once; ``what`` (a flag) names it in the error for a file that is
    none."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{what} {path} does not exist (make one with `swimm train-detector`)")
    saved = _load(path)
    if not isinstance(saved, dict) or saved.get("format") != DETECTOR_FORMAT:
        raise ValueError(f"{what} {path} is not a {DETECTOR_FORMAT} checkpoint")
    if saved.get("version") != DETECTOR_VERSION:
        raise ValueError(f"{what} {path} is a {DETECTOR_FORMAT} checkpoint of version {saved.get('version')!r}; this "
                         f"code reads version {DETECTOR_VERSION}")  # fmt: skip
    return saved


def load_detector(path: str | Path) -> tuple[PodDetector, dict[str, Any]]:
    """A pod detector checkpoint's network in eval mode, and the checkpoint's contents (threshold, history)."""
    saved = read_detector(path)
    model = PodDetector(width=int(saved["width"]), stride=int(saved["stride"]))
    model.load_state_dict(saved["state_dict"])
    return model.eval(), saved


def save_detector(model: PodDetector, path: Path, threshold: float, history: list[dict[str, Any]]) -> None:
    torch.save({"format": DETECTOR_FORMAT, "version": DETECTOR_VERSION, "width": model.width, "stride": model.stride,
                "threshold": threshold, "state_dict": model.state_dict(), "history": history}, path)  # fmt: skip


class PodEncoder:
    """Detector plus tracker behind the encoder interface the in-process env and the scripted tracker use."""

    tracks = True
    n_z = N_Z
    labels = LABEL_NAMES
    prior_shape = (STATE_SIZE,)

    def __init__(
        self,
        checkpoint: str | Path,
        tracker: PodTracker | None = None,
        threads: int | None = None,
        engine: str = "torch",
    ) -> None:
        if engine not in ENGINES:
            raise ValueError(f"encoder engine must be one of {', '.join(ENGINES)}, got {engine!r}")
        if threads is not None:
            torch.set_num_threads(threads)  # process-wide, as a CMVAE's LatentEncoder does
        self.model, saved = load_detector(checkpoint)
        self.engine = engine
        self._detect: Callable[[torch.Tensor], tuple[torch.Tensor, ...]] = self.model
        if engine == "onnx":
            example = (images_to_tensor(np.zeros((1, *IMAGE_SHAPE), np.uint8)),)
            self._detect = onnx_runtime(self.model, example, ["images"], ["heat", "regression"], threads)
        self.threshold = float(saved["threshold"])
        self.tracker = tracker or PodTracker()
        self.checkpoint = Path(checkpoint)
        log.info("pod detector %s loaded (threshold %.2f), %s engine", checkpoint, self.threshold, engine)

    @torch.inference_mode()
    def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each frame's target latent (mu, logvar) and the tracker state to hand back with the next frame; a prior
        of None (or all zeros) starts tracking afresh: the engagement frame."""
        check_images(images)
        if priors is not None and (np.shape(priors) != (len(images), STATE_SIZE) or not np.isfinite(priors).all()):
            raise ValueError(f"priors must be {len(images)} finite pod tracker states of {STATE_SIZE} numbers, one "
                             f"per frame, got an array shaped {np.shape(priors)}")  # fmt: skip
        detections = self.detect(images)
        states = np.zeros((len(images), STATE_SIZE), np.float32)
        readings = np.zeros((len(images), 3))  # d, theta and psi (unread: 0) of each frame's target
        for row, frame in enumerate(detections):
            prior = None if priors is None or not np.any(priors[row]) else priors[row]
            states[row], reading = self.tracker.update(prior, frame)
            readings[row, :2] = reading or UNSEEN
        mu = np.zeros((len(images), N_Z), np.float32)
        mu[:, :3] = normalise_labels(readings)
        return mu, np.zeros_like(mu), states

    @torch.inference_mode()
    def detect(self, images: np.ndarray) -> list[Detections]:
        """Every dolphin the detector finds in each frame, with its look (no tracking)."""
        return decode(
            *self._detect(images_to_tensor(images)), self.threshold, images.shape[1], self.model.stride, images
        )

    def encode(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        mu, logvar, _ = self.track(images, priors)
        return mu, logvar

    def decode_state(self, mu: np.ndarray) -> tuple[np.ndarray, ...]:
        """(d m, theta deg, psi deg) arrays from latents (N, n_z), as a CMVAE's decoders give them."""
        return tuple(denormalise_labels(np.asarray(mu)[:, :3]).T)
