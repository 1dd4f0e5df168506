"""The MuJoCo world, its lock-step responder and dataset generation.

MuJoCo chooses its OpenGL backend when it is first imported. Without a
display, the only one that works is EGL (a GPU's, or Mesa's llvmpipe on a
CPU), so it is the default here; set MUJOCO_GL yourself to override it.
"""

import os

if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")
