"""Counters and latency percentiles, published periodically on ``<ns>/metrics/<role>/<id>``."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from typing import Any, Protocol

import msgpack
import numpy as np
import zenoh

from services.keys import Keys
from services.lifecycle import Owner

log = logging.getLogger(__name__)


class Metrics:
    """Thread-safe counters plus a sliding window of latencies (milliseconds)."""

    def __init__(self, window: int = 2048) -> None:
        self._lock = threading.Lock()
        self._counters: Counter[str] = Counter()
        self._latencies: dict[str, deque[float]] = {}
        self._window = window

    def count(self, name: str, amount: int = 1) -> None:
        with self._lock:
            self._counters[name] += amount

    def observe_ms(self, name: str, value_ms: float) -> None:
        with self._lock:
            self._latencies.setdefault(name, deque(maxlen=self._window)).append(value_ms)

    def snapshot(self) -> dict[str, float]:
        with self._lock:
            snap: dict[str, float] = dict(self._counters)
            for name, values in self._latencies.items():
                if values:
                    p50, p99 = np.percentile(np.fromiter(values, float), [50, 99])
                    snap[f"{name}_p50_ms"] = float(p50)
                    snap[f"{name}_p99_ms"] = float(p99)
            return snap


class Snapshots(Protocol):
    """Whatever has numbers to publish: :class:`Metrics`, or a learner's progress."""

    def snapshot(self) -> dict[str, Any]: ...


class MetricsPublisher(Owner):
    """Publishes a :class:`Metrics` (or other :class:`Snapshots`) snapshot every ``period_s`` from a daemon thread."""

    def __init__(
        self, session: zenoh.Session, keys: Keys, role: str, ident: str, metrics: Snapshots, period_s: float = 2.0
    ):
        self._publisher = self.resources.enter_context(session.declare_publisher(keys.metrics(role, ident)))
        self._metrics = metrics
        self._period_s = period_s
        self._role, self._ident = role, ident
        self._stop = threading.Event()
        thread = threading.Thread(target=self._run, name=f"metrics-{role}", daemon=True)
        thread.start()
        # Closed in reverse: the thread is told to stop, then joined, then the publisher goes.
        self.resources.callback(thread.join, timeout=period_s + 1)
        self.resources.callback(self._stop.set)

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self.publish()

    def publish(self) -> None:
        body = {"role": self._role, "id": self._ident, "t": time.time(), **self._metrics.snapshot()}
        try:
            self._publisher.put(msgpack.packb(body))
        except zenoh.ZError as exc:  # a closing session must not kill the service
            log.debug("metrics not published: %s", exc)
