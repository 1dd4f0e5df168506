"""Plays deterministic evaluation episodes of one policy on one env and turns every step into metric rows.

The training callback's evaluations and `swimm eval` share it, so it lives with the learner, below both.

The env is either the distributed :class:`learner_service.proxy_env.ProxyEnv` or the in-process
:class:`learner_service.inprocess_env.TrackingEnv`: both give the same ``info`` (telemetry, cause, d, theta,
azimuth, psi, ep, seed), so this module never knows which one it drives. Per-step rows go to a callback as
they happen (the CSV writer, the live view), so a long evaluation never holds its steps in memory.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from learner_service.metrics import EpisodeMetrics, elevation_error, pod_identity
from learner_service.registry import Policy
from services.geometry import ALPHA_DEG, MAX_D, OPT_D

log = logging.getLogger(__name__)

#: Columns of the per-step CSV, in order (plots.STEP_COLUMNS are among them).
STEP_FIELDS = (
    "label", "episode", "seed", "step", "t", "surge", "yaw_cmd", "reward", "return_so_far", "d", "theta", "azimuth",
    "psi", "A", "D", "S_D", "S_A", "in_frustum", "distance_exceeded", "collided", "cause",
    "rover_x", "rover_y", "rover_z", "rover_yaw", "target_x", "target_y", "target_z", "target_yaw",
)  # fmt: skip
#: What a 3d task's step rows add: the signed elevation and unsigned error (degrees), the step's term of E, and the
#: heave command with its smoothness.
VERTICAL_STEP_FIELDS = ("elevation", "phi", "E", "heave", "S_H")
#: What a pod's step rows add: the dolphin the rover follows (0 the target, -1 none) and whether the target is hidden
#: by a companion (services/identity.py).
IDENTITY_STEP_FIELDS = ("followed", "target_occluded")

StepSink = Callable[[dict[str, Any]], None]


@dataclass(frozen=True)
class Contender:
    """One policy to evaluate: its label in tables and figures, its algorithm, and its checkpoint (None: scripted)."""

    label: str
    algo: str
    checkpoint: str | None = None


def step_row(
    label: str,
    episode: int,
    seed: int,
    step: int,
    action: np.ndarray,
    reward: float,
    total: float,
    info: dict[str, Any],
    smooth: dict[str, float],
) -> dict[str, Any]:
    """One CSV row: the step's action, reward, geometry, per-step metric terms (``smooth`` by name) and both poses.

    Yaws are the headings of the bodies' forward vectors in the horizontal plane (degrees, counter-clockwise
    from +x), which is what the top-down trajectory plot draws. A 3d task's rows add VERTICAL_STEP_FIELDS, a pod's
    IDENTITY_STEP_FIELDS.
    """
    telemetry = info["telemetry"]
    rover_yaw = math.degrees(math.atan2(telemetry.rover_forward[1], telemetry.rover_forward[0]))
    target_yaw = math.degrees(math.atan2(telemetry.target_forward[1], telemetry.target_forward[0]))
    d, theta = float(info["d"]), float(info["theta"])
    row = {
        "label": label, "episode": episode, "seed": seed, "step": step, "t": time.time(),
        "surge": float(action[0]), "yaw_cmd": float(action[-1]), "reward": float(reward), "return_so_far": total,
        "d": d, "theta": theta, "azimuth": float(info["azimuth"]), "psi": float(info["psi"]),
        "A": min(abs(theta), ALPHA_DEG) / ALPHA_DEG, "D": abs(d - OPT_D) / MAX_D,
        "S_D": smooth["S_D"], "S_A": smooth["S_A"],
        "in_frustum": bool(telemetry.target_in_frustum), "distance_exceeded": abs(d - OPT_D) >= MAX_D,
        "collided": bool(telemetry.collided), "cause": info["cause"],
        "rover_x": float(telemetry.rover_pos[0]), "rover_y": float(telemetry.rover_pos[1]),
        "rover_z": float(telemetry.rover_pos[2]), "rover_yaw": rover_yaw,
        "target_x": float(telemetry.target_pos[0]), "target_y": float(telemetry.target_pos[1]),
        "target_z": float(telemetry.target_pos[2]), "target_yaw": target_yaw,
    }  # fmt: skip
    if "phi" in info:
        row |= {"elevation": float(info["elevation"]), "phi": float(info["phi"]), "E": elevation_error(info["phi"])}
    if "S_H" in smooth:
        row |= {"heave": float(action[1]), "S_H": smooth["S_H"]}
    if telemetry.pod_size > 1:
        row |= {"followed": telemetry.followed, "target_occluded": telemetry.target_occluded}
    return row


def play_episodes(
    policy: Policy,
    env: gym.Env,
    label: str,
    episodes: int,
    seed: int,
    options: dict[str, Any] | None = None,
    on_step: StepSink | None = None,
    on_episode: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """``episodes`` deterministic episodes from base seed ``seed``; returns one summary row per episode.

    ``reset(seed=seed)`` restarts the env's episode sequence, so the same seed plays the same episodes for every
    policy (the world's episode seeds are ``episode_seed(seed, 1..N)``, recorded in the rows). The env must have
    early termination off: an evaluation episode runs its full length whatever happens. ``options`` are every
    reset's (``noise``, ``latency``: the world's conditions; left out, the env keeps what it has).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    rows = []
    for episode in range(1, episodes + 1):
        obs, info = env.reset(seed=seed, options=options) if episode == 1 else env.reset(options=options)
        episode_seed = int(info["seed"])
        metrics = EpisodeMetrics(label, episode)
        started = time.perf_counter()
        done = False
        while not done:
            action = np.asarray(policy.act(obs, info), dtype=np.float32).reshape(-1)
            obs, reward, terminated, truncated, info = env.step(action)
            telemetry = info["telemetry"]
            smooth = metrics.add(info["d"], info["theta"], telemetry.target_in_frustum, telemetry.collided, action,
                                 float(reward), info.get("phi"), pod_identity(telemetry))  # fmt: skip
            if on_step is not None:
                on_step(step_row(label, episode, episode_seed, metrics.steps, action, float(reward),
                                 metrics.total_reward, info, smooth))  # fmt: skip
            if terminated:
                raise RuntimeError("the evaluation env ended an episode early; build it with early_termination=False")
            done = truncated
        row = metrics.row() | {"seed": episode_seed, "steps": metrics.steps}
        log.info("%s episode %d (seed %d): return %.1f over %d steps in %.1f s, first violation %s", label, episode,
                 episode_seed, row["return"], metrics.steps, time.perf_counter() - started,
                 row["first_cause"] or "none")  # fmt: skip
        if on_episode is not None:
            on_episode(row)
        rows.append(row)
    return rows
