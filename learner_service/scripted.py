"""Scripted baselines: a proportional controller on ground truth, the yardstick a learned policy must beat, and
the same controller on the CMVAE's reading of the camera frame, a camera-only baseline with nothing learnt
but the encoder.

`ScriptedTracker` reads the telemetry the envs put in ``info`` (never the observation), so it runs unchanged in
every observation mode and needs no checkpoint. `LatentTracker` reads the observation's latent mean only.
Sign conventions (the sim's, ArduSub's): positive azimuth = target to the
left; positive yaw command turns the nose left (counter-clockwise seen from
above, z up); positive surge drives forward.
"""

from __future__ import annotations

import math
from collections.abc import Callable
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
        return self.command(geometry.d, geometry.azimuth)

    def command(self, d: float, azimuth: float) -> np.ndarray:
        """(surge, yaw) in [-1, 1] for a target ``d`` metres away at ``azimuth`` degrees (+ = left)."""
        surge = self.surge_gain * (d - OPT_D) * math.cos(math.radians(azimuth))
        yaw = self.yaw_gain * azimuth
        return np.clip(np.array([surge, yaw], dtype=np.float32), -1.0, 1.0)


class LatentTracker(ScriptedTracker):
    """The tracker's control law on the distance and azimuth that the CMVAE's state decoders read from the latent.

    Camera only, like a learned policy on cmvae observations, and nothing to train: it separates what the encoder
    can see (under noise, say) from what a policy learns to do with it. ``decode`` maps latents (N, n_z) to
    (d, theta, psi) arrays, as `encoder_service.inference.LatentEncoder.decode_state` does.
    """

    def __init__(self, decode: Callable[[np.ndarray], tuple[np.ndarray, ...]], n_z: int) -> None:
        super().__init__()
        self.decode = decode
        self.n_z = n_z

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """(surge, yaw) from the latent mean at the head of a cmvae observation; ``info`` is ignored."""
        latent = np.asarray([] if isinstance(obs, dict) else obs, dtype=np.float32).reshape(-1)
        if latent.size < self.n_z:
            raise ValueError(f"the latent tracker reads cmvae observations (a latent of {self.n_z} values first)")
        d, theta, _ = self.decode(latent[None, : self.n_z])
        return self.command(float(d[0]), float(theta[0]))
