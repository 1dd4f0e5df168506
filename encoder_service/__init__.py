#: The CMVAE's inference engines (encoder_service.inference), here so that launchers can check a choice without torch.
ENGINES = ("torch", "onnx")


def check_engine(engine: str, flag: str) -> None:
    """Refuse an unknown engine by the ``flag`` that named it, before any process is started."""
    if engine not in ENGINES:
        raise ValueError(f"{flag} must be one of {', '.join(ENGINES)}, got {engine!r}")
