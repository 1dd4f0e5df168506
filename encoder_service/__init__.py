"""The CMVAE service. This module holds what launchers and evaluators need without importing torch."""

from pathlib import Path

#: The shipped CMVAE (docs/encoder.md): every command's encoder when none is given.
DEFAULT_CHECKPOINT = Path(__file__).parent / "models" / "cmvae.pt"

#: The CMVAE's inference engines (encoder_service.inference), here so that launchers can check a choice without torch.
ENGINES = ("torch", "onnx")


def check_engine(engine: str, flag: str) -> None:
    """Refuse an unknown engine by the ``flag`` that named it, before any process is started."""
    if engine not in ENGINES:
        raise ValueError(f"{flag} must be one of {', '.join(ENGINES)}, got {engine!r}")
