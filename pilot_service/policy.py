"""An exported policy (`swimm export`) under onnxruntime, holding its own action history (ActPrev) and, for a
tracking CMVAE, where its target was last seen (the prior); for a policy on the pod detector, the detector's file
beside it and the tracker that reads the target from its peaks (services.pod_tracker)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.messages import POLICY_ACTIONS
from services.pod_tracker import TargetReader, TrackerParams
from services.results import file_sha256

INPUTS = {"frame", "action_history"}
#: A policy on the pod detector reads the tracker's (distance, azimuth) of the target instead of the frame.
READING_INPUTS = {"reading", "action_history"}
OUTPUTS = {"action", "next_history"}
#: The state a file feeds back, as (input, the output that is its next value): a tracking CMVAE's prior optional.
CARRIED = {"action_history": "next_history", "prior": "next_prior"}
#: The actions a policy may drive: the planar task's, and the 3d task's with heave (a climb rate in ALT_HOLD).
ACTION_SETS = [list(names) for names in POLICY_ACTIONS.values()]


class ContractError(ValueError):
    """An ONNX file that is not a swimm camera-to-action policy; the message says what does not match."""


class OnnxPolicy:
    """Frame in, (surge, yaw) or (surge, heave, yaw) out; the history (and a tracking CMVAE's prior) the file feeds
    back is kept here and cleared by ``reset``."""

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime  # the pilot extra: loaded only when a policy is

        if not Path(path).is_file():
            raise ContractError(f"no policy file at {path}; make one with `swimm export --out {path}`")
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        try:
            self.session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for a file it cannot load
            raise ContractError(f"{path} is not an ONNX model onnxruntime can load: {exc}") from None
        inputs = {node.name: node.shape for node in self.session.get_inputs()}
        outputs = {node.name for node in self.session.get_outputs()}
        metadata = self.session.get_modelmeta().custom_metadata_map
        tracks = "prior" in inputs  # a policy on a tracking CMVAE
        reads = "reading" in inputs  # a policy on the pod detector
        wanted_in = READING_INPUTS if reads else INPUTS | {"prior"} if tracks else INPUTS
        wanted_out = OUTPUTS | {"next_prior"} if tracks else OUTPUTS
        if set(inputs) != wanted_in or not wanted_out <= outputs or "swimm.contract" not in metadata:
            raise ContractError(f"{path} is not a swimm policy: inputs {sorted(inputs)}, outputs {sorted(outputs)}, "
                                f"metadata {sorted(metadata)}; expected inputs {sorted(wanted_in)} and outputs "
                                f"{sorted(wanted_out)} with swimm.contract (written by `swimm export`)")  # fmt: skip
        self.carried = {name: (CARRIED[name], tuple(inputs[name][1:])) for name in CARRIED if name in inputs}
        self.contract = json.loads(metadata["swimm.contract"])
        self.reader = target_reader(Path(path), self.contract.get("perception"), threads) if reads else None
        self.image_size = self.reader.size if self.reader else int(inputs["frame"][1])
        self.history_size = int(inputs["action_history"][1])
        self.control_rate_hz = float(self.contract.get("control_rate_hz", 50))
        self.action_names = list(self.contract.get("action_names", ACTION_SETS[0]))
        if self.action_names not in ACTION_SETS:
            flown = " or ".join(map(str, ACTION_SETS))
            raise ContractError(f"{path} drives {self.action_names}; the pilot flies {flown}")
        width = next(node.shape[1] for node in self.session.get_outputs() if node.name == "action")
        if width != len(self.action_names):
            raise ContractError(f"{path} outputs {width} actions but its contract names {self.action_names}")
        self.reset()

    @property
    def tracks(self) -> bool:
        """Whether a target can be pointed out to the policy: it reads a prior (a tracking CMVAE) or its tracker
        engages a dolphin (the pod detector)."""
        return "prior" in self.carried or self.reader is not None

    def reset(self, prior_deg: float = 0.0) -> None:
        """A new episode: an empty history and the target the dolphin at ``prior_deg`` (its azimuth; by default the
        image centre, as at every training episode's start): the prior there, or the tracker engaging afresh."""
        if prior_deg and not self.tracks:
            raise ContractError("only a policy on a tracking CMVAE or the pod detector takes a target's azimuth: this "
                                "one follows the dolphin the camera is centred on")  # fmt: skip
        self.state = {name: np.zeros((1, *shape), np.float32) for name, (_, shape) in self.carried.items()}
        if "prior" in self.state:
            self.state["prior"][:] = prior_deg
        if self.reader is not None:
            self.reader.reset(prior_deg)

    def act(self, frame: np.ndarray) -> np.ndarray:
        """The action for one RGB frame of the contract's size."""
        expected = (self.image_size, self.image_size, 3)
        if frame.shape != expected or frame.dtype != np.uint8:
            raise ContractError(f"the policy takes uint8 frames of shape {expected}, got {frame.dtype} {frame.shape}")
        seen = {"frame": frame[None]}
        if self.reader is not None:
            seen = {"reading": np.float32([self.reader.read(frame)])}
        action, *carried = self.session.run(["action", *(output for output, _ in self.carried.values())],
                                            seen | self.state)  # fmt: skip
        self.state = dict(zip(self.carried, carried, strict=True))
        return action[0]


def target_reader(policy: Path, perception: dict | None, threads: int) -> TargetReader:
    """The detector file a policy on the pod detector names, checked to be the one it was exported with, behind the
    tracker its contract describes."""
    import onnxruntime

    if not isinstance(perception, dict) or perception.get("kind") != "pod-detector":
        raise ContractError(f"{policy} reads a target's reading but its contract names no pod detector")
    detector = policy.parent / str(perception.get("detector"))
    if not detector.is_file():
        raise ContractError(f"{policy} reads its frames through {detector}, which does not exist: keep the two files "
                            "`swimm export` wrote side by side")  # fmt: skip
    if file_sha256(detector) != perception.get("detector_sha256"):
        raise ContractError(f"{detector} is not the detector {policy} was exported with (its sha256 differs): export "
                            "the pair again")  # fmt: skip
    try:
        params = TrackerParams(**perception["tracker"])
        threshold, stride = float(perception["threshold"]), int(perception["stride"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ContractError(f"{policy}: its contract's tracker, threshold or stride cannot be read ({exc})") from None
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    session = onnxruntime.InferenceSession(str(detector), options, providers=["CPUExecutionProvider"])
    size = int(session.get_inputs()[0].shape[1])
    return TargetReader(lambda frames: session.run(None, {"frame": frames}), threshold, stride, size, params)
