"""An exported policy (`swimm export`) under onnxruntime, holding its own action history (ActPrev)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.messages import POLICY_ACTIONS

INPUTS = {"frame", "action_history"}
OUTPUTS = {"action", "next_history"}
#: The actions a policy may drive: the planar task's, and the 3d task's with heave (a climb rate in ALT_HOLD).
ACTION_SETS = [list(names) for names in POLICY_ACTIONS.values()]


class ContractError(ValueError):
    """An ONNX file that is not a swimm camera-to-action policy; the message says what does not match."""


class OnnxPolicy:
    """Frame in, (surge, yaw) or (surge, heave, yaw) out; the history the file feeds back is kept here and cleared
    by ``reset``."""

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
        if set(inputs) != INPUTS or not OUTPUTS <= outputs or "swimm.contract" not in metadata:
            raise ContractError(f"{path} is not a swimm policy: inputs {sorted(inputs)}, outputs {sorted(outputs)}, "
                                f"metadata {sorted(metadata)}; expected inputs {sorted(INPUTS)} and outputs "
                                f"{sorted(OUTPUTS)} with swimm.contract (written by `swimm export`)")  # fmt: skip
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

    def reset(self) -> None:
        """A new episode: an empty history, as the policy met at every training episode's start."""
        self.history = np.zeros((1, self.history_size), np.float32)

    def act(self, frame: np.ndarray) -> np.ndarray:
        """The action for one RGB frame of the contract's size."""
        expected = (self.image_size, self.image_size, 3)
        if frame.shape != expected or frame.dtype != np.uint8:
            raise ContractError(f"the policy takes uint8 frames of shape {expected}, got {frame.dtype} {frame.shape}")
        action, self.history = self.session.run(["action", "next_history"],
                                                {"frame": frame[None], "action_history": self.history})  # fmt: skip
        return action[0]
