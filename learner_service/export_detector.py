"""`swimm export` of a policy on the pod detector: the detector and the actor as two ONNX files, the tracker between.

The tracker (services.pod_tracker) keeps identity across frames by a matching no ONNX graph expresses, so the pair
splits where it runs, and the caller (`swimm pilot`, :class:`services.pod_tracker.TargetReader`) joins them:

    <out stem>.detector.onnx  frame uint8 (N, 64, 64, 3), RGB -> heat (N, G, G), peak scores in (0, 1), and
                              regression (N, 3, G, G): each cell's sub-cell offset and log distance
    <out>                     reading float32 (N, 2): the target's distance (m) and azimuth (deg, + = left) as the
                              tracker reads them, (6, 0) before a dolphin is engaged; action_history -> action,
                              next_history, as a CMVAE policy's file

The actor file's contract names the detector file with its sha256, the peak threshold, the grid's stride and the
tracker's parameters. The check plays a real in-process episode on the detector and tracker under torch with the
stable-baselines3 model choosing every action; the pair under onnxruntime, joined by the same tracker, must read the
same targets and choose the same actions.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoder_service.model import LABEL_NAMES, label_ranges
from encoder_service.pod_detector import PodDetector
from encoder_service.pod_encoder import PodEncoder, load_detector
from learner_service.policy_graph import LatentToAction, contract, play, write_onnx
from learner_service.task import LATENT_SIZE, TrackingTask
from services.messages import IMAGE_SHAPE
from services.pod_tracker import TargetReader, TrackerParams
from services.results import file_sha256

#: What a reading's difference is a share of in the check: the state decoders' [-1, 1] stretched over each range.
READING_UNITS = (label_ranges(LABEL_NAMES)[:2, 1] - label_ranges(LABEL_NAMES)[:2, 0]) / 2


class FrameToPeaks(torch.nn.Module):
    """uint8 RGB frames in, the detector's peak scores and regression out (its frame normalisation inside)."""

    def __init__(self, detector: PodDetector) -> None:
        super().__init__()
        self.detector = detector

    def forward(self, frame: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        images = frame.permute(0, 3, 1, 2).float() / 127.5 - 1.0  # encoder_service.model.images_to_tensor
        logits, regression = self.detector(images)
        return torch.sigmoid(logits[:, 0]), regression


class ReadingToAction(torch.nn.Module):
    """The tracker's reading and ActPrev in, action and the next ActPrev out: the reading placed in the latent as the
    detector's encoder places it (normalised d, theta and a psi of 0; the rest 0), then the actor."""

    def __init__(self, policy: Any, history_size: int) -> None:
        super().__init__()
        self.act = LatentToAction(policy, history_size)
        low, high = torch.as_tensor(label_ranges(LABEL_NAMES), dtype=torch.float32).T
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, reading: torch.Tensor, action_history: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        labels = torch.cat([reading, torch.zeros_like(reading[:, :1])], dim=1)  # psi unread: 0
        normalised = 2.0 * (labels - self.low) / (self.high - self.low) - 1.0
        rest = torch.zeros_like(reading[:, :1]).repeat(1, LATENT_SIZE - normalised.shape[1])
        return self.act(torch.cat([normalised, rest], dim=1), action_history)


def detector_file(out: Path) -> Path:
    """Where the actor file at ``out`` keeps its detector: beside it, ``<stem>.detector.onnx``."""
    return out.with_name(f"{out.stem}.detector.onnx")


def perception(name: str, sha256: str, saved: dict[str, Any], params: TrackerParams) -> dict[str, Any]:
    """The contract's part that says how frames become the actor's reading: the detector file ``name`` (beside the
    actor's) with its ``sha256``, its checkpoint's threshold and stride, the tracker's ``params``."""
    return {"kind": "pod-detector", "detector": name, "detector_sha256": sha256,
            "threshold": float(saved["threshold"]), "stride": int(saved["stride"]), "tracker": asdict(params),
            "reading": "float32 (N, 2): the target's distance (m) and azimuth (deg, + = left) from the pod "
                       "tracker over the detector's peaks (services.pod_tracker.TargetReader), (6, 0) before "
                       "engagement"}  # fmt: skip


def recorded_episode(model: Any, task: TrackingTask, detector: Path, frames: int, seed: int) -> dict[str, np.ndarray]:
    """The Python path played in process: each frame, whether it engaged afresh, the target reading the detector and
    tracker gave, ActPrev and the chosen action."""
    seen: list[tuple[np.ndarray, bool, np.ndarray]] = []

    class Recording(PodEncoder):
        def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
            mu, logvar, states = super().track(images, priors)
            reading = np.stack(self.decode_state(mu)[:2], axis=1)[0].astype(np.float32)
            seen.append((images[0].copy(), priors is None or not np.any(priors[0]), reading))
            return mu, logvar, states

    played = play(model, task, Recording(detector), seen, frames, seed)
    frame, engage, reading = (np.stack(column) for column in zip(*seen[:frames], strict=True))
    return {"frame": frame, "engage": engage, "reading": reading} | played


def verify_pair(actor: Path, detector: Path, saved: dict[str, Any], recorded: dict[str, np.ndarray],
                tolerance: float) -> dict[str, float]:  # fmt: skip
    """Run the pair under onnxruntime, joined by the tracker, on the recorded frames (engaging afresh where the
    episode did); the largest reading and action differences from the Python path, and the latency."""
    import onnxruntime  # the export extra: only where a file is checked

    detect_session, act_session = (onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
                                   for path in (detector, actor))  # fmt: skip
    reader = TargetReader(lambda frames: detect_session.run(None, {"frame": frames}), float(saved["threshold"]),
                          int(saved["stride"]), IMAGE_SHAPE[0])  # fmt: skip
    readings, actions = [], []
    started = time.perf_counter()
    for frame, engage, history in zip(recorded["frame"], recorded["engage"], recorded["action_history"], strict=True):
        if engage:
            reader.reset()
        readings.append(np.float32(reader.read(frame)))
        feeds = {"reading": readings[-1][None], "action_history": history[None]}
        actions.append(act_session.run(["action"], feeds)[0][0])
    per_frame_ms = (time.perf_counter() - started) * 1000 / len(actions)
    report = {}
    for name, got, unit in (("reading", readings, READING_UNITS), ("action", actions, 1.0)):
        difference = np.abs(np.stack(got) - recorded[name]) / unit
        if not difference.max() <= tolerance:
            raise ValueError(f"{actor}: the pair under onnxruntime gives a {name} that differs from the Python "
                             f"path's by up to {difference.max():.2e} of its unit (allowed {tolerance:.1e}); the "
                             "files are not kept")  # fmt: skip
        report[f"max_{name}_difference"] = float(difference.max())
    return report | {"onnx_ms_per_frame": per_frame_ms}


def export_detector_policy(
    model: Any, task: TrackingTask, detector: Path, out: Path, source: tuple[str, Path], check_frames: int,
    check_seed: int, tolerance: float,
) -> dict[str, Any]:  # fmt: skip
    """Write and check the pair for ``model`` on ``detector``; ``source`` is the algorithm and file the model was
    loaded from, for the contract. Nothing is left at ``out`` or beside it unless the check passes."""
    network, saved = load_detector(detector)
    detector_out = detector_file(out)
    partials = [path.with_name(path.name + ".partial") for path in (detector_out, out)]
    example = torch.zeros(1, *IMAGE_SHAPE, dtype=torch.uint8)
    try:
        write_onnx(FrameToPeaks(network).eval(), (example,), ["frame"], ["heat", "regression"], partials[0], {})
        reads = perception(detector_out.name, file_sha256(partials[0]), saved, TrackerParams())
        metadata = contract(*source, detector, task, {"reading": "float32 (N, 2), see perception"},
                            "frame / 127.5 - 1, inside the detector file's graph", perception=reads)  # fmt: skip
        actor = ReadingToAction(model.policy.eval(), task.history_size).eval()
        actor_example = (torch.zeros(1, 2), torch.zeros(1, task.history_size))
        write_onnx(
            actor, actor_example, ["reading", "action_history"], ["action", "next_history"], partials[1], metadata
        )
        recorded = recorded_episode(model, task, detector, check_frames, check_seed)
        report = verify_pair(partials[1], partials[0], saved, recorded, tolerance)
    except BaseException:
        for path in partials:
            path.unlink(missing_ok=True)
        raise
    for partial, final in zip(partials, (detector_out, out), strict=True):
        partial.replace(final)
    return report | {"detector_onnx": str(detector_out), "detector_bytes": detector_out.stat().st_size}
