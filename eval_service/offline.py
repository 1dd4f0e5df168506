"""`swimm eval --recording FILE`: the episodes of a `swimm record` file scored offline, with no sim and no policy.

A recording holds each env's observations (telemetry: the ground truth the metrics read) and the actions that led
to them, keyed by (episode, step). An episode is scored as a live evaluation scores it: step k's action with the
world after it, through the same reward and Table 12 metrics (learner_service.metrics). Re-sent steps appear twice
on the wire and count once. Each step message may carry a group of envs; each env's items are read on their own.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from pathlib import Path
from typing import Any

from learner_service.learn_settings import RewardVersion, TaskName
from learner_service.metrics import EpisodeMetrics, pod_identity
from learner_service.task import TrackingTask, frame_reward, policy_action
from services.keys import CHANNELS
from services.messages import ActionMsg, BadMessage, ObservationMsg, batch_messages
from services.record import recorded_namespace, recorded_samples
from services.telemetry import Telemetry

log = logging.getLogger(__name__)


class RecordedEpisode:
    """One env's episode as recorded: telemetry after each step, and each step's sim command."""

    def __init__(self) -> None:
        self.telemetry: dict[int, Telemetry] = {}
        self.actions: dict[int, tuple[float, ...]] = {}  # (sway, heave, surge, yaw)

    def steps(self) -> list[int]:
        """The steps with both their action and the world after it, in order, from 1 without a gap."""
        played = []
        while (step := len(played) + 1) in self.actions and step in self.telemetry:
            played.append(step)
        return played


def recorded_episodes(path: str | Path) -> dict[tuple[str, str, int], RecordedEpisode]:
    """Every (channel, env, episode) of a recording, read from its observation and action keys."""
    namespace = recorded_namespace(path)
    episodes: dict[tuple[str, str, int], RecordedEpisode] = defaultdict(RecordedEpisode)
    for key, payload, _ in recorded_samples(path):
        parts = key[len(namespace) + 1 :].split("/")
        if len(parts) < 3 or parts[0] not in CHANNELS:
            continue
        channel, kind = parts[0], parts[2]
        try:
            if kind == "obs":
                for env, msg in batch_messages(payload, ObservationMsg.from_item):
                    episodes[(channel, env, msg.ep)].telemetry.setdefault(msg.seq, msg.telemetry)
            elif kind == "action":
                for env, action in batch_messages(payload, ActionMsg.from_item):
                    episodes[(channel, env, action.ep)].actions.setdefault(action.seq, tuple(action.action))
        except BadMessage as exc:
            log.warning("%s: skipped an unreadable %s message on %s: %s", path, kind, key, exc)
    return dict(episodes)


def score_recording(
    path: str | Path, reward: RewardVersion = "swimm2", task: TaskName = "planar"
) -> list[dict[str, Any]]:
    """One Table 12 row per recorded episode with at least one step, labelled ``<channel>/<env>``."""
    rows = []
    for (channel, env, ep), episode in sorted(recorded_episodes(path).items()):
        steps = episode.steps()
        if not steps:
            continue
        metrics = EpisodeMetrics(f"{channel}/{env}", ep)
        for step in steps:
            telemetry = episode.telemetry[step]
            info = TrackingTask.info(telemetry, task)
            action = policy_action(episode.actions[step], task)
            metrics.add(info["d"], info["theta"], telemetry.target_in_frustum, telemetry.collided, action,
                        frame_reward(info, reward), info.get("phi"), pod_identity(telemetry))  # fmt: skip
        rows.append(metrics.row() | {"seed": None, "steps": metrics.steps})
    if not rows:
        raise ValueError(f"{path} holds no scorable episode (no env's actions with the observations after them)")
    return rows
