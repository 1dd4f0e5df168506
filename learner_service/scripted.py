"""A scripted baseline: a proportional controller on ground truth, the yardstick a learned policy must beat.

It reads the telemetry the envs put in ``info`` (never the observation), so
it runs unchanged in every observation mode and needs no checkpoint.
Sign conventions (the sim's, ArduSub's): positive azimuth = target to the
left; positive yaw command turns the nose left (counter-clockwise seen from
above, z up); positive surge drives forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.geometry import OPT_D, relative_geometry
from services.telemetry import Telemetry


@dataclass
class ScriptedTracker:
    """Yaw toward the target's azimuth and close the distance error along the current heading.

    Surge is ``surge_gain * (d - opt_d) * cos(azimuth)``: the distance error projected on the nose, so the
    rover does not drive away from a target that is beside or behind it while it turns.
    """

    # Defaults from a sweep on the in-process env (3 evaluation episodes, seed 113): yaw gains above ~1/45 per
    # degree make the heading oscillate (A and S_A grow), lower ones lag the dolphin; surge gain matters less.
    yaw_gain: float = 1.0 / 60.0  # command per degree of azimuth: full turn at 60 degrees
    surge_gain: float = 1.0  # command per metre of distance error: full surge 1 m off opt_d

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """(surge, yaw) in [-1, 1] from ``info["telemetry"]``; ``obs`` is ignored."""
        telemetry = info.get("telemetry")
        if not isinstance(telemetry, Telemetry):
            raise ValueError("the scripted tracker needs info['telemetry'] (a services.telemetry.Telemetry)")
        geometry = relative_geometry(telemetry)
        surge = self.surge_gain * (geometry.d - OPT_D) * math.cos(math.radians(geometry.azimuth))
        yaw = self.yaw_gain * geometry.azimuth
        return np.clip(np.array([surge, yaw], dtype=np.float32), -1.0, 1.0)
