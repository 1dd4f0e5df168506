"""The CMVAE service. This module holds what launchers and evaluators need without importing torch."""

from pathlib import Path
from typing import Literal, get_args

#: The shipped CMVAE (docs/encoder.md): every command's encoder when none is given.
DEFAULT_CHECKPOINT = Path(__file__).parent / "models" / "cmvae.pt"

#: The shipped pod detector (docs/encoder.md, "Every dolphin, then which one"): an encoder for pods, not a default.
POD_DETECTOR = Path(__file__).parent / "models" / "pod_detector.pt"

#: A pod detector checkpoint's format name (encoder_service.pod_encoder): the CMVAE loaders refuse one by name.
DETECTOR_FORMAT = "swimm-pod-detector"

#: The CMVAE's inference engines (encoder_service.inference), here so that launchers' settings can name the choice
#: without importing torch: a settings field of this type refuses any other by its flag.
Engine = Literal["torch", "onnx"]
ENGINES: tuple[str, ...] = get_args(Engine)
