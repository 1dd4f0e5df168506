"""Scripted baselines: a proportional controller on ground truth, the yardstick a learned policy must beat, and
the same controller on the CMVAE's reading of the camera frame, a camera-only baseline with nothing learnt
but the encoder.

`ScriptedTracker` reads the telemetry the envs put in ``info``, and of the observation only ActPrev (when
damped), so it runs unchanged in every observation mode and needs no checkpoint. `LatentTracker` reads the
observation's latent mean (and ActPrev) only.
Sign conventions (the sim's, ArduSub's): positive azimuth = target to the
left; positive yaw command turns the nose left (counter-clockwise seen from
above, z up); positive surge drives forward.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from learner_service.learn_settings import TrackerGains
from learner_service.task import ACTION_SIZE, TaskSettings
from services.geometry import OPT_D, relative_geometry
from services.telemetry import Telemetry

ACT_PREV_SIZE = TaskSettings().history_size  # ActPrev as the task's observations carry it


def commanded_yaw(obs: Any) -> float:
    """The mean yaw command of the observation's ActPrev (its ``actions`` key, or the flat observation's tail)."""
    history = obs["actions"] if isinstance(obs, dict) else np.asarray(obs, np.float32).reshape(-1)[-ACT_PREV_SIZE:]
    return float(np.mean(np.asarray(history, np.float32)[1::ACTION_SIZE]))


@dataclass
class ScriptedTracker:
    """Yaw toward the target's azimuth and close the distance error along the current heading.

    Surge is ``surge_gain * (d - opt_d) * cos(azimuth)``: the distance error projected on the nose, so the
    rover does not drive away from a target that is beside or behind it while it turns.
    """

    gains: TrackerGains = field(default_factory=TrackerGains)

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """(surge, yaw) in [-1, 1] from ``info["telemetry"]`` (and ActPrev from ``obs`` when damped)."""
        telemetry = info.get("telemetry")
        if not isinstance(telemetry, Telemetry):
            raise ValueError("the scripted tracker needs info['telemetry'] (a services.telemetry.Telemetry)")
        geometry = relative_geometry(telemetry)
        return self.command(geometry.d, geometry.azimuth, obs)

    def command(self, d: float, azimuth: float, obs: Any = None) -> np.ndarray:
        """(surge, yaw) in [-1, 1] for a target ``d`` metres away at ``azimuth`` degrees (+ = left)."""
        gains = self.gains
        surge = gains.surge_gain * (d - OPT_D) * math.cos(math.radians(azimuth))
        yaw = gains.yaw_gain * azimuth
        if gains.yaw_damping:
            yaw -= gains.yaw_damping * commanded_yaw(obs)
        return np.clip(np.array([surge, yaw], dtype=np.float32), -1.0, 1.0)


class LatentTracker(ScriptedTracker):
    """The tracker's control law on the distance and azimuth that the CMVAE's state decoders read from the latent.

    Camera only, like a learned policy on cmvae observations, and nothing to train: it separates what the encoder
    can see (under noise, say) from what a policy learns to do with it. ``decode`` maps latents (N, n_z) to
    (d, theta, psi) arrays, as `encoder_service.inference.LatentEncoder.decode_state` does.
    """

    def __init__(
        self, decode: Callable[[np.ndarray], tuple[np.ndarray, ...]], n_z: int, gains: TrackerGains | None = None
    ) -> None:
        super().__init__(gains or TrackerGains())
        self.decode = decode
        self.n_z = n_z

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """(surge, yaw) from the latent mean at the head of a cmvae observation; ``info`` is ignored."""
        latent = np.asarray([] if isinstance(obs, dict) else obs, dtype=np.float32).reshape(-1)
        if latent.size < self.n_z:
            raise ValueError(f"the latent tracker reads cmvae observations (a latent of {self.n_z} values first)")
        d, theta, _ = self.decode(latent[None, : self.n_z])
        return self.command(float(d[0]), float(theta[0]), obs)
