"""The pieces `swimm export` builds its files from, whatever the encoder: the actor as a torch module of a latent,
an ONNX writer that stamps the contract into the file, and a real in-process episode to check a file against."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learner_service.registry import deterministic_action
from learner_service.task import TrackingTask

OPSET = 17


class LatentToAction(torch.nn.Module):
    """A latent and ActPrev in, the action and the next ActPrev out: the actor, then what stable-baselines3's
    ``predict`` does after the network."""

    def __init__(self, policy: Any, history_size: int) -> None:
        super().__init__()
        self.policy = policy
        self.history_size = history_size
        low, high = (torch.as_tensor(bound, dtype=torch.float32) for bound in (policy.action_space.low,
                                                                              policy.action_space.high))  # fmt: skip
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, mu: torch.Tensor, action_history: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        actions = deterministic_action(self.policy, torch.cat([mu, action_history], dim=1))
        if self.policy.squash_output:  # back from the squashed [-1, 1], else clipped to the bounds
            actions = self.low + 0.5 * (actions + 1.0) * (self.high - self.low)
        action = torch.minimum(torch.maximum(actions, self.low), self.high)
        return action, torch.cat([action_history[:, action.shape[1] :], action], dim=1)


def write_onnx(
    graph: torch.nn.Module,
    example: tuple[torch.Tensor, ...],
    inputs: Sequence[str],
    outputs: Sequence[str],
    path: Path,
    metadata: dict[str, str],
) -> None:
    """``graph`` (eval mode) as an ONNX file at ``path``, any batch size, ``metadata`` in its ``metadata_props``."""
    import onnx  # the export extra: only where a file is written

    # Argument checks of torch.distributions (the actor builds one even for its deterministic action) would be traced
    # as constant branches; the graph needs none of them.
    torch.distributions.Distribution.set_default_validate_args(False)
    try:
        with torch.no_grad():
            torch.onnx.export(graph, example, str(path), input_names=list(inputs), output_names=list(outputs),
                              opset_version=OPSET, dynamo=False,
                              dynamic_axes={name: {0: "batch"} for name in (*inputs, *outputs)})  # fmt: skip
    finally:
        torch.distributions.Distribution.set_default_validate_args(__debug__)  # torch's default
    model = onnx.load(str(path))
    for key, value in metadata.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(path))


def play(model: Any, task: TrackingTask, encoder: Any, seen: list, frames: int, seed: int) -> dict[str, np.ndarray]:
    """Play the model deterministically in process for ``frames`` steps on ``encoder``, which appends a row to
    ``seen`` for each frame it reads; each step's ActPrev and chosen action. The row of a frame that ended an episode
    is dropped (the one before the reset's): it is never acted on."""
    from learner_service.inprocess_env import TrackingEnv  # MuJoCo: not in the torch image, which attaches only

    env = TrackingEnv(task.settings, base_seed=seed, encoder=encoder)
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
                del seen[-2]
    finally:
        env.close()
    return {"action_history": np.stack(histories), "action": np.stack(actions)}
