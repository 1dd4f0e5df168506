"""A small pod dataset rendered by the real sim (MuJoCo offscreen), with masks, for the pod perception tests."""

from __future__ import annotations

import os
from pathlib import Path


def render_pod_dataset(root: Path, count: int, shard_size: int, pod_size: int = 3) -> Path:
    """``count`` frames of a pod of ``pod_size`` (seed 4) with the target's and companions' masks, written under
    ``root``."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; read when MuJoCo is first imported
    from sim_service.dataset import write_dataset
    from sim_service.settings import DolphinSettings, WorldSettings

    world = WorldSettings(render=True, dolphin=DolphinSettings(pod_size=pod_size))
    return write_dataset(root, count=count, seed=4, shard_size=shard_size, world_settings=world, progress=False,
                         masks=True)  # fmt: skip
