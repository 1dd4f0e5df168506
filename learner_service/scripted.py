"""Scripted baselines: a proportional controller on ground truth, the yardstick a learned policy must beat, and
the same controller on the CMVAE's reading of the camera frame, a camera-only baseline with nothing learnt
but the encoder.

`ScriptedTracker` reads the telemetry the envs put in ``info``, and of the observation only ActPrev (when
damped), so it runs unchanged in every observation mode and needs no checkpoint. `LatentTracker` reads the
observation's latent mean (and ActPrev) only.
Both act in the task that ``info`` belongs to: (surge, yaw) in the planar task, (surge, heave, yaw) in the 3d task,
whose ``info`` carries the elevation (learner_service.task.TrackingTask.info).
Sign conventions (the sim's, ArduSub's): positive azimuth = target to the
left; positive yaw command turns the nose left (counter-clockwise seen from
above, z up); positive surge drives forward; positive elevation = target above; positive heave climbs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from learner_service.learn_settings import TrackerGains
from learner_service.task import TaskSettings
from services.geometry import OPT_D, relative_geometry
from services.telemetry import Telemetry


def commanded_yaw(obs: Any, action_size: int = 2) -> float:
    """The mean yaw command (the last component of each action) of the observation's ActPrev: its ``actions`` key,
    or the flat observation's tail, of actions of ``action_size`` components."""
    history_size = TaskSettings().n_prev_actions * action_size  # ActPrev as the task's observations carry it
    history = obs["actions"] if isinstance(obs, dict) else np.asarray(obs, np.float32).reshape(-1)[-history_size:]
    return float(np.mean(np.asarray(history, np.float32)[action_size - 1 :: action_size]))


def task_elevation(info: dict[str, Any]) -> float | None:
    """The target's signed elevation (degrees) in the 3d task's ``info``; None in the planar task's."""
    return info.get("elevation")


@dataclass
class ScriptedTracker:
    """Yaw toward the target's azimuth, close the distance error along the current heading, and in the 3d task
    climb or dive toward the target's elevation.

    Surge is ``surge_gain * (d - opt_d) * cos(azimuth)``: the distance error projected on the nose, so the
    rover does not drive away from a target that is beside or behind it while it turns. Heave is
    ``heave_gain * elevation`` (target above: climb), 0 within ``heave_dead_band`` degrees so that depth hold
    keeps the rover still while the target is near the camera's horizon.
    """

    gains: TrackerGains = field(default_factory=TrackerGains)

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """The task's action in [-1, 1] from ``info["telemetry"]`` (and ActPrev from ``obs`` when damped)."""
        telemetry = info.get("telemetry")
        if not isinstance(telemetry, Telemetry):
            raise ValueError("the scripted tracker needs info['telemetry'] (a services.telemetry.Telemetry)")
        geometry = relative_geometry(telemetry)
        return self.command(geometry.d, geometry.azimuth, obs, task_elevation(info))

    def command(self, d: float, azimuth: float, obs: Any = None, elevation: float | None = None) -> np.ndarray:
        """(surge, yaw) in [-1, 1] for a target ``d`` metres away at ``azimuth`` degrees (+ = left); with an
        ``elevation`` in degrees (+ = above), the 3d task's (surge, heave, yaw)."""
        gains = self.gains
        surge = gains.surge_gain * (d - OPT_D) * math.cos(math.radians(azimuth))
        yaw = gains.yaw_gain * azimuth
        if gains.yaw_damping:
            yaw -= gains.yaw_damping * commanded_yaw(obs, 2 if elevation is None else 3)
        action = [surge, yaw] if elevation is None else [surge, self.heave(elevation), yaw]
        return np.clip(np.array(action, dtype=np.float32), -1.0, 1.0)

    def heave(self, elevation: float) -> float:
        """The heave law: proportional to the elevation beyond the dead band (unclipped)."""
        return 0.0 if abs(elevation) < self.gains.heave_dead_band else self.gains.heave_gain * elevation


class LatentTracker(ScriptedTracker):
    """The tracker's control law on the distance and azimuth that the CMVAE's state decoders read from the latent.

    Camera only, like a learned policy on cmvae observations, and nothing to train: it separates what the encoder
    can see (under noise, say) from what a policy learns to do with it. ``decode`` maps latents (N, n_z) to
    (d, theta, psi[, elevation]) arrays, as `encoder_service.inference.LatentEncoder.decode_state` does.

    In the 3d task it heaves on the elevation a vertical CMVAE reads; on a planar CMVAE, which reads none, its
    heave is 0 (the rover holds its depth). Of ``info`` it reads only which task it acts in.
    """

    def __init__(
        self, decode: Callable[[np.ndarray], tuple[np.ndarray, ...]], n_z: int, gains: TrackerGains | None = None
    ) -> None:
        super().__init__(gains or TrackerGains())
        self.decode = decode
        self.n_z = n_z

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        """The task's action from the latent mean at the head of a cmvae observation."""
        latent = np.asarray([] if isinstance(obs, dict) else obs, dtype=np.float32).reshape(-1)
        if latent.size < self.n_z:
            raise ValueError(f"the latent tracker reads cmvae observations (a latent of {self.n_z} values first)")
        d, theta, *rest = (float(values[0]) for values in self.decode(latent[None, : self.n_z]))
        elevation = None
        if task_elevation(info) is not None:
            elevation = rest[1] if len(rest) > 1 else 0.0  # a planar CMVAE reads none: act as if the target were level
        return self.command(d, theta, obs, elevation)
