"""The images' package boundaries: each service imports without the heavy packages its image leaves out.

deploy/Dockerfile.sim installs the sim group (no torch); deploy/Dockerfile.torch the encoder, learner and
eval groups (no MuJoCo). A module that reaches across (the learner's task importing a MuJoCo helper, say)
only fails inside the container, so this test imports each side in a fresh interpreter where the other
side's packages cannot be found.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

BLOCKER = """
import importlib.abc, sys
class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (left out of this image)")
        return None
sys.meta_path.insert(0, Missing())
import {modules}
print("imported")
"""

SIDES = {
    "torch image (no MuJoCo)": (
        {"mujoco"},
        ["learner_service.command", "learner_service.proxy_env", "eval_service.command", "eval_service.attach",
         "encoder_service.service", "swimm.cli"],
    ),
    "sim image (no torch)": (
        {"torch", "stable_baselines3", "gymnasium"},
        ["sim_service.responder", "sim_service.dataset", "sim_service.world", "swimm.cli", "learner_service.up"],
    ),
    "shared core (neither)": (
        {"torch", "mujoco", "stable_baselines3", "gymnasium", "cv2"},
        ["services.settings", "services.session", "services.messages", "services.geometry", "services.presence",
         "services.low_latency"],
    ),
}  # fmt: skip


@pytest.mark.parametrize("side", SIDES)
def test_each_side_imports_without_the_packages_its_image_leaves_out(side: str) -> None:
    blocked, modules = SIDES[side]
    code = BLOCKER.format(blocked=blocked, modules=", ".join(modules))
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "imported"
