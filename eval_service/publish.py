"""Evaluation results on ``<ns>/metrics/eval/<id>``: each finished episode and each summary, as msgpack maps.

Other services' metrics there are periodic counters; an evaluator's are events (an episode ended, a checkpoint
was scored), so it puts one message per event: ``{"role": "eval", "id", "t", "kind": "episode" | "summary", ...}``.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

import msgpack
import numpy as np
import zenoh

from services.keys import Keys
from services.lifecycle import Owner
from services.presence import announce
from services.session import open_session
from services.settings import ZenohSettings

log = logging.getLogger(__name__)


class ResultPublisher(Owner):
    """Owns a session, a liveliness token (role ``eval``) and the publisher of this evaluator's metrics key."""

    def __init__(self, zenoh_settings: ZenohSettings, ident: str = "") -> None:
        self.ident = ident or f"eval-{os.getpid()}"
        self.keys = Keys(zenoh_settings.namespace)
        self.key = self.keys.metrics("eval", self.ident)
        session = self.resources.enter_context(open_session(zenoh_settings, role="eval"))
        self.resources.enter_context(announce(session, self.keys, "eval", self.ident))
        publisher = session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.BLOCK)
        self._publisher = self.resources.enter_context(publisher)

    def publish(self, kind: str, body: dict[str, Any]) -> None:
        message = {"role": "eval", "id": self.ident, "t": time.time(), "kind": kind, **_plain(body)}
        self._publisher.put(msgpack.packb(message, use_bin_type=True))
        log.debug("published %s on %s", kind, self.key)


def _plain(body: dict[str, Any]) -> dict[str, Any]:
    """msgpack-safe values: numpy scalars become Python numbers, nested maps are converted too."""
    out: dict[str, Any] = {}
    for key, value in body.items():
        if isinstance(value, dict):
            value = _plain(value)
        elif isinstance(value, np.generic):
            value = value.item()
        out[str(key)] = value
    return out
