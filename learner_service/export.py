"""`swimm export`: a trained camera-only policy as one ONNX file, from camera frame to action.

The file is the contract between training and a vehicle: it holds the CMVAE encoder (its mean), the actor and the
scaling to the action range, and it carries the action history (ActPrev) as an input and an output, so the caller
keeps the only state there is:

    inputs   frame           uint8 (N, 64, 64, 3), RGB, as the sim's camera renders it
             action_history  float32 (N, 20): ActPrev, the last 10 actions oldest first, zeros at an episode's start
    outputs  action          float32 (N, 2): (surge, yaw) in [-1, 1]
             next_history    float32 (N, 20): action_history with the action appended (feed it back next frame)

The rest of the contract (sizes, colour order, normalisation, control rate, action names, where it came from) is in
the model's metadata (``metadata_props``), which `verify` and a pilot read. Before the file is kept it is checked
against the Python path: a deterministic episode of real frames is played in-process with the stable-baselines3
model choosing every action, and onnxruntime must give the same actions from the same frames and histories.
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
from encoder_service.model import load_model
from learner_service.identity import encoder_for, policy_task
from learner_service.registry import deterministic_action, resolve_algorithm
from learner_service.task import LATENT_SIZE, TaskSettings, TrackingTask
from services.results import file_sha256
from sim_service.settings import WorldSettings

log = logging.getLogger(__name__)

SHIPPED_POLICY = Path(__file__).parent / "models" / "sac_cmvae_general.zip"  # the policy to fly (docs/learner.md)
INPUTS = ("frame", "action_history")
OUTPUTS = ("action", "next_history")
OPSET = 17


@dataclass
class ExportSettings:
    algo: str = "sac"  # the algorithm that saved the checkpoint
    checkpoint: str = ""  # a saved cmvae-observation model (.zip); default: the shipped policy
    encoder_checkpoint: str = ""  # the CMVAE the policy was trained on; default: the one the policy records
    out: str = "runs/export/policy.onnx"
    check_frames: int = 1000  # frames of a real in-process episode both paths must agree on
    check_seed: int = 9001  # the episode's seed
    tolerance: float = 1e-4  # largest allowed |onnx - python| action difference
    threads: int = 1  # torch CPU threads of the Python path (docs/eval.md: one is faster beside other work)


class CameraToAction(torch.nn.Module):
    """Frame and ActPrev in, action and the next ActPrev out: the encoder's mean feeding the actor."""

    def __init__(self, encoder: torch.nn.Module, policy: Any, history_size: int) -> None:
        super().__init__()
        self.encoder = encoder
        self.policy = policy
        self.history_size = history_size
        low, high = (torch.as_tensor(bound, dtype=torch.float32) for bound in (policy.action_space.low,
                                                                              policy.action_space.high))  # fmt: skip
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, frame: torch.Tensor, action_history: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        images = frame.permute(0, 3, 1, 2).float() / 127.5 - 1.0  # encoder_service.model.images_to_tensor
        mu, _ = self.encoder(images)
        actions = deterministic_action(self.policy, torch.cat([mu, action_history], dim=1))
        # What BasePolicy.predict does after the network: back from the squashed [-1, 1] or clip to the bounds.
        if self.policy.squash_output:
            actions = self.low + 0.5 * (actions + 1.0) * (self.high - self.low)
        action = torch.minimum(torch.maximum(actions, self.low), self.high)
        next_history = torch.cat([action_history[:, action.shape[1] :], action], dim=1)
        return action, next_history


#: How the vehicle holds or changes depth under each task's actions (`swimm pilot` flies heave in ALT_HOLD only).
DIVE_MODES = {
    "planar": "depth_hold (sway and heave held at 0)",
    "3d": "depth_hold (heave a climb rate, sway held at 0)",
}


def contract(settings: ExportSettings, policy_path: Path, encoder_path: Path, task: TrackingTask) -> dict[str, str]:
    """The file's metadata: what a caller must feed it and where it came from (values are strings in ONNX)."""
    names = task.settings.action_names
    return {
        "swimm.contract": json.dumps(
            {
                "inputs": {
                    "frame": "uint8 NHWC (N, 64, 64, 3), RGB, the sim camera's 64x64 render (79.95 deg HFOV)",
                    "action_history": f"float32 (N, {task.history_size}): the last {task.settings.n_prev_actions} "
                    "actions, oldest first, zeros at an episode's start",
                },
                "outputs": {
                    "action": f"float32 (N, {len(names)}) in [-1, 1]",
                    "next_history": "the next action_history",
                },
                "normalisation": "frame / 127.5 - 1, inside the graph",
                "action_names": list(names),
                "task": task.settings.task,
                "dive_mode": DIVE_MODES[task.settings.task],
                "control_rate_hz": round(1.0 / WorldSettings().physics_dt),
            }
        ),
        "swimm.algo": settings.algo,
        "swimm.policy_sha256": file_sha256(policy_path),
        "swimm.encoder_sha256": file_sha256(encoder_path),
    }


def episode_frames(model: Any, task: TrackingTask, encoder_path: Path, frames: int, seed: int) -> dict[str, np.ndarray]:
    """Play the model deterministically in-process for ``frames`` steps: every frame, ActPrev and chosen action."""
    from learner_service.inprocess_env import TrackingEnv  # MuJoCo: not in the torch image, which attaches only

    seen: list[np.ndarray] = []

    class Recording(LatentEncoder):
        def encode(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            seen.append(images[0].copy())
            return super().encode(images)

    env = TrackingEnv(task.settings, base_seed=seed, encoder=Recording(encoder_path))
    histories, actions = [], []
    try:
        obs, _ = env.reset()
        while len(actions) < frames:
            action, _ = model.predict(obs, deterministic=True)
            histories.append(obs[-task.history_size :].copy())
            actions.append(np.asarray(action, dtype=np.float32))
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                obs, _ = env.reset()
                seen.pop()  # the frame that ended the episode is never acted on
    finally:
        env.close()
    return {"frame": np.stack(seen[:frames]), "action_history": np.stack(histories), "action": np.stack(actions)}


def torch_latency_ms(model: Any, encoder_path: Path, recorded: dict[str, np.ndarray]) -> float:
    """The Python path's time per frame on the same frames: the CMVAE encoder, then the model's predict."""
    encoder = LatentEncoder(encoder_path)
    started = time.perf_counter()
    for frame, history in zip(recorded["frame"], recorded["action_history"], strict=True):
        mu, _ = encoder.encode(frame[None])
        model.predict(np.concatenate([mu[0], history]), deterministic=True)
    return (time.perf_counter() - started) * 1000 / len(recorded["frame"])


def verify(path: Path, recorded: dict[str, np.ndarray], tolerance: float) -> dict[str, float]:
    """Run the ONNX file under onnxruntime on recorded frames; the largest action difference and the latency."""
    import onnxruntime  # the export extra: only where a file is checked

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    started = time.perf_counter()
    actions = [session.run(["action"], {"frame": frame[None], "action_history": history[None]})[0][0]
               for frame, history in zip(recorded["frame"], recorded["action_history"], strict=True)]  # fmt: skip
    per_frame_ms = (time.perf_counter() - started) * 1000 / len(actions)
    difference = float(np.abs(np.stack(actions) - recorded["action"]).max())
    if not difference <= tolerance:
        raise ValueError(f"{path}: onnxruntime's actions differ from the Python path's by up to {difference:.2e} "
                         f"(allowed {tolerance:.0e}); the file is not kept")  # fmt: skip
    return {"max_action_difference": difference, "onnx_ms_per_frame": per_frame_ms}


def run(settings: ExportSettings) -> int:
    if settings.check_frames < 1 or settings.tolerance <= 0:
        raise ValueError("check_frames must be >= 1 and tolerance > 0")
    if settings.threads > 0:
        torch.set_num_threads(settings.threads)
    policy_path = Path(settings.checkpoint) if settings.checkpoint else SHIPPED_POLICY
    # the encoder the policy records, refusing another one by name; the shipped CMVAE for a policy recording none
    encoder_path = encoder_for(policy_path, settings.encoder_checkpoint or None) or DEFAULT_CHECKPOINT
    if not encoder_path.is_file():
        raise FileNotFoundError(f"CMVAE checkpoint {encoder_path} does not exist")
    cls, _ = resolve_algorithm(settings.algo)
    model = cls.load(policy_path, device="cpu")
    task = TrackingTask(TaskSettings(obs="cmvae", task=policy_task(policy_path)))  # its actions are the task's
    expected = (LATENT_SIZE + task.history_size,)
    if model.observation_space.shape != expected:
        raise ValueError(f"{policy_path} observes {model.observation_space.shape}, not cmvae's {expected}: only "
                         "camera-only (cmvae) policies export")  # fmt: skip
    cmvae, _ = load_model(encoder_path, "cpu")
    graph = CameraToAction(cmvae.encoder.float(), model.policy.eval(), task.history_size).eval()
    out = Path(settings.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    example = (torch.zeros(1, 64, 64, 3, dtype=torch.uint8), torch.zeros(1, task.history_size))
    # Argument checks of torch.distributions (the actor builds one even for its deterministic action) would be traced
    # as constant branches; the graph needs none of them.
    torch.distributions.Distribution.set_default_validate_args(False)
    try:
        with torch.no_grad():
            torch.onnx.export(graph, example, str(partial), input_names=list(INPUTS), output_names=list(OUTPUTS),
                              dynamic_axes={name: {0: "batch"} for name in INPUTS + OUTPUTS}, opset_version=OPSET,
                              dynamo=False)  # fmt: skip
    finally:
        torch.distributions.Distribution.set_default_validate_args(__debug__)  # torch's default
    import onnx  # the export extra: only where a file is written

    onnx_model = onnx.load(str(partial))
    for key, value in contract(settings, policy_path, encoder_path, task).items():
        onnx_model.metadata_props.add(key=key, value=value)
    onnx.save(onnx_model, str(partial))
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
