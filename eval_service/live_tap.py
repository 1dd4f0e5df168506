"""Feeding the live view from an env someone else drives (``--live-env train/0``): a passive Zenoh listener.

It subscribes to every group's actions and observations on the env's channel, on every route
(``<ns>/<ch>/*/obs/*``: the env may be stepped alone or in a learner's group), keeps the env's items, and
recomputes what the holder's task computes from the same telemetry: the geometry, the reward and the running
Table 12 terms. It never sends anything, so the training it watches is exactly what it would be without it.
Replayed observations (a retried step) are shown once.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np
import zenoh

from eval_service.live import LiveFeed
from learner_service.evaluation import step_row
from learner_service.learn_settings import RewardVersion, TaskName
from learner_service.metrics import EpisodeMetrics, pod_identity
from learner_service.task import TrackingTask, frame_reward, policy_action
from services.keys import CHANNELS, Keys, check_chunk
from services.lifecycle import Owner
from services.messages import ActionMsg, BadMessage, ObservationMsg, batch_messages
from services.session import open_session
from services.settings import ZenohSettings

log = logging.getLogger(__name__)
KEPT_MESSAGES = 64  # actions (and observations) kept until their other half arrives
UNKNOWN_SEED = -1  # the episode seed travels in the holder's reset request, which a viewer does not see


def parse_env(name: str) -> tuple[str, str]:
    """``"train/0"`` -> ("train", "0"), refusing anything else with the expected form."""
    channel, _, env = name.partition("/")
    if channel not in CHANNELS or not env:
        raise ValueError(f"--live-env wants <channel>/<env> with channel in {CHANNELS}, e.g. train/0; got {name!r}")
    return channel, check_chunk(env, "env id")


class EnvTap(Owner):
    """Pushes each new step of ``<channel>/<env>`` into ``feed`` under the source name ``"<channel>/<env>"``."""

    def __init__(
        self,
        zenoh_settings: ZenohSettings,
        name: str,
        feed: LiveFeed,
        reward: RewardVersion = "swimm2",
        task: TaskName = "planar",
    ) -> None:
        self.channel, self.env = parse_env(name)
        self.source = f"{self.channel}/{self.env}"
        self.feed = feed
        self._reward = reward
        self._task = task
        self._lock = threading.Lock()
        self._actions: dict[tuple[int, int], np.ndarray] = {}
        self._observations: dict[tuple[int, int], ObservationMsg] = {}
        self._last = (-1, -1)  # (ep, seq) of the last step recorded
        self._episode: EpisodeMetrics | None = None
        keys = Keys(zenoh_settings.namespace)
        session = self.resources.enter_context(open_session(zenoh_settings, role="eval"))
        self.resources.enter_context(session.declare_subscriber(keys.actions(self.channel), self._on_action))
        self.resources.enter_context(session.declare_subscriber(keys.obs(self.channel, "*", "*"), self._on_obs))
        log.info("live view taps %s", self.source)

    def _on_action(self, sample: zenoh.Sample) -> None:
        try:
            actions = [
                msg for env, msg in batch_messages(sample.payload.to_bytes(), ActionMsg.from_item) if env == self.env
            ]
        except BadMessage:
            return  # the sim refuses and logs bad actions; the viewer just ignores them
        with self._lock:
            for msg in actions:
                self._actions[(msg.ep, msg.seq)] = policy_action(msg.action, self._task)
            self._drain()

    def _on_obs(self, sample: zenoh.Sample) -> None:
        try:
            frames = [msg for env, msg in batch_messages(sample.payload.to_bytes(), ObservationMsg.from_item)
                      if env == self.env]  # fmt: skip
        except BadMessage:
            return
        with self._lock:
            for msg in frames:
                if msg.seq > 0:  # a reset's frame has no action; the episode starts with its first step
                    self._observations[(msg.ep, msg.seq)] = msg
            self._drain()

    def _drain(self) -> None:
        """Record, in step order, every step whose action and observation have both arrived.

        The two come from different publishers (learner and sim) and may reach this subscriber in either order.
        """
        for key in sorted(self._observations.keys() & self._actions.keys()):
            msg, action = self._observations.pop(key), self._actions.pop(key)
            if key > self._last:  # an older key is a replayed observation of a retried step
                self._record(msg, action)
                self._last = key
        for pending in (self._observations, self._actions):
            for key in sorted(pending)[:-KEPT_MESSAGES]:
                del pending[key]  # their other half was lost (or the tap joined between them)

    def _record(self, msg: ObservationMsg, action: np.ndarray) -> None:
        if self._episode is None or msg.ep != self._episode.episode:
            self._episode = EpisodeMetrics(self.source, msg.ep)
        info: dict[str, Any] = TrackingTask.info(msg.telemetry, self._task)
        reward = frame_reward(info, self._reward)
        smooth = self._episode.add(info["d"], info["theta"], msg.telemetry.target_in_frustum, msg.telemetry.collided,
                                   action, reward, info.get("phi"), pod_identity(msg.telemetry))  # fmt: skip
        total = self._episode.total_reward
        row = step_row(self.source, msg.ep, UNKNOWN_SEED, msg.seq, action, reward, total, info, smooth)
        self.feed.update(self.source, row, msg.image)
