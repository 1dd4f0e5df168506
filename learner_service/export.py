"""`swimm export`: a trained camera-only policy as one ONNX file, from camera frame to action.

The file is the contract between training and a vehicle: it holds the CMVAE encoder (its mean), the actor and the
scaling to the action range, and it carries the action history (ActPrev) as an input and an output, so the caller
keeps the only state there is:

    inputs   frame           uint8 (N, 64, 64, 3), RGB, as the sim's camera renders it
             action_history  float32 (N, 20): ActPrev, the last 10 actions oldest first, zeros at an episode's start
             prior           float32 (N,): a tracking CMVAE's only: degrees (+ = left) where its target was last
                             seen, zeros at an episode's start
    outputs  action          float32 (N, 2): (surge, yaw) in [-1, 1]
             next_history    float32 (N, 20): action_history with the action appended (feed it back next frame)
             next_prior      float32 (N,): a tracking CMVAE's only: the azimuth the latent decodes to (feed it back)

The rest of the contract (sizes, colour order, normalisation, control rate, action names, where it came from) is in
the model's metadata (``metadata_props``), which `verify` and a pilot read. Before the file is kept it is checked
against the Python path: a deterministic episode of real frames is played in-process with the stable-baselines3
model choosing every action, and onnxruntime must give the same actions from the same frames and histories (and
a tracking CMVAE's next priors from the same priors).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoder_service import DEFAULT_CHECKPOINT
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, LABEL_RANGES, PriorReader, load_model, refuse_distance_prior
from encoder_service.pod_encoder import is_detector
from learner_service.export_detector import export_detector_policy
from learner_service.identity import encoder_for, policy_task
from learner_service.policy_graph import LatentToAction, contract, play, write_onnx
from learner_service.registry import resolve_algorithm
from learner_service.task import LATENT_SIZE, TaskSettings, TrackingTask
from services.settings import FilePath, PosFloat, PosInt, check_ranges

log = logging.getLogger(__name__)

#: The policy to fly (docs/learner.md): sac_cmvae_wide.zip's weights, rebound to fly on cmvae_fans.pt (`swimm rebind`).
SHIPPED_POLICY = Path(__file__).parent / "models" / "sac_cmvae_fans.zip"
INPUTS = ("frame", "action_history")
OUTPUTS = ("action", "next_history")
#: What a tracking CMVAE's file carries besides: where its target was last seen, fed back as ActPrev is.
TRACKING_INPUTS = ("prior",)
TRACKING_OUTPUTS = ("next_prior",)
#: The unit the check's tolerance is a share of, per output: actions span [-1, 1]; a next prior is in degrees, the
#: state decoder's [-1, 1] stretched over the azimuth range (float32 rounding grows with it).
CHECK_UNITS = {"action": 1.0, "next_prior": (LABEL_RANGES["theta"][1] - LABEL_RANGES["theta"][0]) / 2}

#: What the frame and a tracking CMVAE's prior are, for the contract.
FRAME = "uint8 NHWC (N, 64, 64, 3), RGB, the sim camera's 64x64 render (79.95 deg HFOV)"
PRIOR = ("float32 (N,): degrees (+ = left) where the CMVAE's target was last seen, zeros at an episode's start (the "
         "image centre: the target is the dolphin the camera is centred on)")  # fmt: skip


@dataclass
class ExportSettings:
    algo: str = "sac"  # the algorithm that saved the checkpoint
    checkpoint: FilePath = ""  # a saved cmvae-observation model (.zip); default: the shipped policy
    encoder_checkpoint: FilePath = ""  # the CMVAE the policy was trained on; default: the one the policy records
    out: str = "runs/export/policy.onnx"
    check_frames: PosInt = 1000  # frames of a real in-process episode both paths must agree on
    check_seed: int = 9001  # the episode's seed
    tolerance: PosFloat = 1e-4  # largest allowed |onnx - python| action difference (a next prior's: of its range)
    # the runtimes place a detector's peaks within a few thousandths of a cell, which the tracker carries on
    detector_tolerance: PosFloat = 1e-2  # the same for a policy on the pod detector (its readings': of their ranges)
    threads: int = 1  # torch CPU threads of the Python path (docs/eval.md: one is faster beside other work)


class CameraToAction(torch.nn.Module):
    """Frame and ActPrev in, action and the next ActPrev out: the encoder's mean feeding the actor. A tracking
    CMVAE's prior comes in too, and the azimuth its latent decodes to goes out as the next frame's prior."""

    def __init__(self, cmvae: CMVAE, policy: Any, history_size: int) -> None:
        super().__init__()
        self.tracks = cmvae.tracks
        self.encoder = PriorReader(cmvae) if self.tracks else cmvae.encoder
        self.act = LatentToAction(policy, history_size)
        self.history_size = history_size

    @property
    def inputs(self) -> tuple[str, ...]:
        return INPUTS + TRACKING_INPUTS if self.tracks else INPUTS

    @property
    def outputs(self) -> tuple[str, ...]:
        return OUTPUTS + TRACKING_OUTPUTS if self.tracks else OUTPUTS

    def example(self) -> tuple[torch.Tensor, ...]:
        """An input of each name in :attr:`inputs`, batch 1, for the exporter's trace."""
        example = (torch.zeros(1, 64, 64, 3, dtype=torch.uint8), torch.zeros(1, self.history_size))
        return example + (torch.zeros(1),) if self.tracks else example

    def forward(self, frame: torch.Tensor, action_history: torch.Tensor,
                prior: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:  # fmt: skip
        images = frame.permute(0, 3, 1, 2).float() / 127.5 - 1.0  # encoder_service.model.images_to_tensor
        # a tracking CMVAE's PriorReader gives the next prior after (mu, logvar): none without a prior
        mu, _, *next_prior = self.encoder(images) if prior is None else self.encoder(images, prior)
        return *self.act(mu, action_history), *next_prior


def episode_frames(model: Any, task: TrackingTask, encoder_path: Path, frames: int, seed: int) -> dict[str, np.ndarray]:
    """Play the model deterministically in-process for ``frames`` steps: every frame, its prior (zeros for a CMVAE
    that does not track) and the next prior the encoder gives, ActPrev and the chosen action."""
    seen: list[tuple[np.ndarray, np.float32, np.float32]] = []

    class Recording(LatentEncoder):
        def encode(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
            mu, logvar = super().encode(images, priors)
            seen.append((images[0].copy(), np.float32(0.0), np.float32(0.0)))  # a CMVAE that does not track
            return mu, logvar

        def track(self, images: np.ndarray, priors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
            mu, logvar, next_priors = super().track(images, priors)
            seen.append((images[0].copy(), np.float32(0.0 if priors is None else priors[0]), next_priors[0]))
            return mu, logvar, next_priors

    played = play(model, task, Recording(encoder_path), seen, frames, seed)
    frame, prior, next_prior = (np.stack(column) for column in zip(*seen[:frames], strict=True))
    return {"frame": frame, "prior": prior, "next_prior": next_prior} | played


def torch_latency_ms(model: Any, encoder_path: Path, recorded: dict[str, np.ndarray]) -> float:
    """The Python path's time per frame on the same frames: the CMVAE encoder, then the model's predict."""
    encoder = LatentEncoder(encoder_path)
    started = time.perf_counter()
    for frame, prior, history in zip(recorded["frame"], recorded["prior"], recorded["action_history"], strict=True):
        mu, _ = encoder.encode(frame[None], prior[None])
        model.predict(np.concatenate([mu[0], history]), deterministic=True)
    return (time.perf_counter() - started) * 1000 / len(recorded["frame"])


def verify(path: Path, recorded: dict[str, np.ndarray], tolerance: float) -> dict[str, float]:
    """Run the ONNX file under onnxruntime on recorded frames (and priors, where it takes them); the largest
    difference of each output it shares with the Python path (actions; a tracking CMVAE's next priors, degrees) and
    the latency."""
    import onnxruntime  # the export extra: only where a file is checked

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    inputs = [node.name for node in session.get_inputs()]
    checked = ["action", *TRACKING_OUTPUTS] if "prior" in inputs else ["action"]
    started = time.perf_counter()
    results = [session.run(checked, {name: recorded[name][i : i + 1] for name in inputs})
               for i in range(len(recorded["frame"]))]  # fmt: skip
    per_frame_ms = (time.perf_counter() - started) * 1000 / len(results)
    report = {}
    for name, got in zip(checked, zip(*results, strict=True), strict=True):
        difference, allowed = float(np.abs(np.concatenate(got) - recorded[name]).max()), tolerance * CHECK_UNITS[name]
        if not difference <= allowed:
            raise ValueError(f"{path}: onnxruntime's {name} differs from the Python path's by up to "
                             f"{difference:.2e} (allowed {allowed:.1e}); the file is not kept")  # fmt: skip
        report[f"max_{name}_difference"] = difference
    return report | {"onnx_ms_per_frame": per_frame_ms}


def policy_files(settings: ExportSettings) -> tuple[Path, Path]:
    """The policy to export and its CMVAE: the one the policy records (another is refused by name), the shipped
    CMVAE for a policy recording none."""
    check_ranges(settings)
    policy_path = Path(settings.checkpoint) if settings.checkpoint else SHIPPED_POLICY
    encoder_path = encoder_for(policy_path, settings.encoder_checkpoint or None) or DEFAULT_CHECKPOINT
    if not encoder_path.is_file():
        raise FileNotFoundError(f"CMVAE checkpoint {encoder_path} does not exist")
    if not is_detector(encoder_path):
        refuse_distance_prior(encoder_path, "swimm export")
    return policy_path, encoder_path


def check(settings: ExportSettings) -> None:
    """Refuse the settings, a file that is no policy, a policy and encoder that are no pair and an unknown
    algorithm, before loading."""
    policy_files(settings)
    resolve_algorithm(settings.algo)


def run(settings: ExportSettings) -> int:
    policy_path, encoder_path = policy_files(settings)
    if settings.threads > 0:
        torch.set_num_threads(settings.threads)
    cls, _ = resolve_algorithm(settings.algo)
    model = cls.load(policy_path, device="cpu")
    task = TrackingTask(TaskSettings(obs="cmvae", task=policy_task(policy_path)))  # its actions are the task's
    expected = (LATENT_SIZE + task.history_size,)
    if model.observation_space.shape != expected:
        raise ValueError(f"{policy_path} observes {model.observation_space.shape}, not cmvae's {expected}: only "
                         "camera-only (cmvae) policies export")  # fmt: skip
    out = Path(settings.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if is_detector(encoder_path):
        return export_on_detector(settings, model, task, policy_path, encoder_path, out)
    cmvae, _ = load_model(encoder_path, "cpu")
    graph = CameraToAction(cmvae.float(), model.policy.eval(), task.history_size).eval()
    partial = out.with_name(out.name + ".partial")
    reads = {"frame": FRAME} | ({"prior": PRIOR} if graph.tracks else {})
    more_outputs = {"next_prior": "the next prior: the azimuth the latent decodes to"} if graph.tracks else {}
    metadata = contract(settings.algo, policy_path, encoder_path, task, reads, "frame / 127.5 - 1, inside the graph",
                        more_outputs)  # fmt: skip
    write_onnx(graph, graph.example(), graph.inputs, graph.outputs, partial, metadata)
    log.info("checking %s against the Python path on %d frames (seed %d)", out, settings.check_frames,
             settings.check_seed)  # fmt: skip
    recorded = episode_frames(model, task, encoder_path, settings.check_frames, settings.check_seed)
    try:
        report = verify(partial, recorded, settings.tolerance)
    except ValueError:
        partial.unlink()
        raise
    partial.replace(out)
    report |= {"torch_ms_per_frame": torch_latency_ms(model, encoder_path, recorded), "onnx": str(out),
               "bytes": out.stat().st_size, "frames_checked": settings.check_frames}  # fmt: skip
    (out.with_suffix(".json")).write_text(json.dumps(report, indent=1) + "\n")
    log.info("wrote %s (%.1f MB): actions agree to %.1e on %d frames; %.2f ms per frame under onnxruntime, %.2f "
             "through torch and stable-baselines3", out, report["bytes"] / 1e6, report["max_action_difference"],
             settings.check_frames, report["onnx_ms_per_frame"], report["torch_ms_per_frame"])  # fmt: skip
    return 0


def export_on_detector(
    settings: ExportSettings, model: Any, task: TrackingTask, policy_path: Path, detector: Path, out: Path
) -> int:
    """A policy on the pod detector: the actor's file and the detector's beside it (learner_service.export_detector)."""
    log.info("exporting %s on the pod detector %s, checked on %d frames (seed %d)", policy_path, detector,
             settings.check_frames, settings.check_seed)  # fmt: skip
    report = export_detector_policy(model, task, detector, out, (settings.algo, policy_path), settings.check_frames,
                                    settings.check_seed, settings.detector_tolerance)  # fmt: skip
    report |= {"onnx": str(out), "bytes": out.stat().st_size, "frames_checked": settings.check_frames}
    out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    log.info("wrote %s and %s: readings agree to %.1e and actions to %.1e on %d frames; %.2f ms per frame under "
             "onnxruntime with the tracker", out, report["detector_onnx"], report["max_reading_difference"],
             report["max_action_difference"], settings.check_frames, report["onnx_ms_per_frame"])  # fmt: skip
    return 0
