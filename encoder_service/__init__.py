#: The CMVAE's inference engines (encoder_service.inference), here so that launchers can check a choice without torch.
ENGINES = ("torch", "onnx")
