"""The pieces `swimm export` builds its files from, whatever the encoder: the actor as a torch module of a latent,
the contract a file carries, an ONNX writer that stamps it into the file, and a real in-process episode to check a
file against."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learner_service.registry import deterministic_action
from learner_service.task import TrackingTask
from services.results import file_sha256
from sim_service.settings import WorldSettings

OPSET = 17

#: How the vehicle holds or changes depth under each task's actions (`swimm pilot` flies heave in ALT_HOLD only).
DIVE_MODES = {
    "planar": "depth_hold (sway and heave held at 0)",
    "3d": "depth_hold (heave a climb rate, sway held at 0)",
}


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


def contract(
    algo: str,
    policy_path: Path,
    encoder_path: Path,
    task: TrackingTask,
    reads: dict[str, str],
    normalisation: str,
    more_outputs: dict[str, str] | None = None,
    perception: dict[str, Any] | None = None,
) -> dict[str, str]:
    """A file's metadata: what a caller must feed it and where it came from (values are strings in ONNX). ``reads``
    names the inputs besides ActPrev, ``more_outputs`` the outputs besides the action and the next ActPrev, and
    ``perception`` how frames become a reading where the file does not take frames itself."""
    names = task.settings.action_names
    history = (f"float32 (N, {task.history_size}): the last {task.settings.n_prev_actions} actions, oldest first, "
               "zeros at an episode's start")  # fmt: skip
    outputs = {"action": f"float32 (N, {len(names)}) in [-1, 1]", "next_history": "the next action_history"}
    described = {
        "inputs": reads | {"action_history": history},
        "outputs": outputs | (more_outputs or {}),
        "normalisation": normalisation,
        "action_names": list(names),
        "task": task.settings.task,
        "dive_mode": DIVE_MODES[task.settings.task],
        "control_rate_hz": round(1.0 / WorldSettings().physics_dt),
    }
    return {
        "swimm.contract": json.dumps(described | ({"perception": perception} if perception else {})),
        "swimm.algo": algo,
        "swimm.policy_sha256": file_sha256(policy_path),
        "swimm.encoder_sha256": file_sha256(encoder_path),
    }


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
