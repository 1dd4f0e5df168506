"""An exported policy (`swimm export`) under onnxruntime, holding its own action history (ActPrev) and, for a
tracking CMVAE, where its target was last seen (the prior)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.messages import POLICY_ACTIONS

INPUTS = {"frame", "action_history"}
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
        wanted_in, wanted_out = (INPUTS | {"prior"}, OUTPUTS | {"next_prior"}) if tracks else (INPUTS, OUTPUTS)
        if set(inputs) != wanted_in or not wanted_out <= outputs or "swimm.contract" not in metadata:
            raise ContractError(f"{path} is not a swimm policy: inputs {sorted(inputs)}, outputs {sorted(outputs)}, "
                                f"metadata {sorted(metadata)}; expected inputs {sorted(wanted_in)} and outputs "
                                f"{sorted(wanted_out)} with swimm.contract (written by `swimm export`)")  # fmt: skip
        self.carried = {name: (CARRIED[name], tuple(inputs[name][1:])) for name in CARRIED if name in inputs}
        self.contract = json.loads(metadata["swimm.contract"])
        self.image_size = int(inputs["frame"][1])
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
        """Whether the file reads a prior (a policy on a tracking CMVAE), so a target can be pointed out to it."""
        return "prior" in self.carried

    def reset(self, prior_deg: float = 0.0) -> None:
        """A new episode: an empty history and the prior at ``prior_deg`` (the azimuth of the dolphin to follow; by
        default the image centre, as at every training episode's start)."""
        if prior_deg and not self.tracks:
            raise ContractError("only a policy on a tracking CMVAE takes a target's azimuth: this one has no prior")
        self.state = {name: np.zeros((1, *shape), np.float32) for name, (_, shape) in self.carried.items()}
        if self.tracks:
            self.state["prior"][:] = prior_deg

    def act(self, frame: np.ndarray) -> np.ndarray:
        """The action for one RGB frame of the contract's size."""
        expected = (self.image_size, self.image_size, 3)
        if frame.shape != expected or frame.dtype != np.uint8:
            raise ContractError(f"the policy takes uint8 frames of shape {expected}, got {frame.dtype} {frame.shape}")
        action, *carried = self.session.run(["action", *(output for output, _ in self.carried.values())],
                                            {"frame": frame[None], **self.state})  # fmt: skip
        self.state = dict(zip(self.carried, carried, strict=True))
        return action[0]
