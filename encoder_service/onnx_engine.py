"""An encoder's network under onnxruntime: exported to ONNX in memory at load and run on the CPU (the encoders'
``engine="onnx"``, for a CMVAE and for the pod detector alike)."""

from __future__ import annotations

import io
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import torch


def onnx_runtime(
    module: torch.nn.Module,
    example: tuple[torch.Tensor, ...],
    inputs: Sequence[str],
    outputs: Sequence[str],
    threads: int | None,
) -> Callable[..., tuple[torch.Tensor, ...]]:
    """``module`` (eval mode) as a function of tensors named ``inputs`` to tensors named ``outputs``, run by
    onnxruntime on ``threads`` CPU threads (default 1); every input and output may have any batch size."""
    try:
        import onnxruntime
    except ImportError as exc:
        raise ValueError("the onnx engine needs onnxruntime: pip install 'swimm[export]'") from exc
    graph = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # torch's notes on its TorchScript-based exporter
        batch_axis = {name: {0: "batch"} for name in (*inputs, *outputs)}
        torch.onnx.export(module, example, graph, input_names=list(inputs), output_names=list(outputs),
                          dynamic_axes=batch_axis, dynamo=False)  # fmt: skip
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads or 1
    options.inter_op_num_threads = 1
    session = onnxruntime.InferenceSession(graph.getvalue(), options, providers=["CPUExecutionProvider"])

    def run(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        feeds = {name: np.ascontiguousarray(tensor.numpy()) for name, tensor in zip(inputs, tensors, strict=True)}
        return tuple(torch.from_numpy(output) for output in session.run(None, feeds))

    return run
