"""A live view of evaluation: the camera frame and the metrics of a chosen environment, in a web page.

The evaluator's step loop pushes each step's row (and the frame the env just observed) into a
:class:`LiveFeed`; a stdlib HTTP server on its own thread serves the page, which polls
``/api/state`` and ``/frame.png`` a few times a second. Nothing here slows the step loop: a step only
swaps references under a lock, and PNG encoding happens when (and only as often as) a browser asks.

Routes: ``/`` the page; ``/api/sources`` the environments seen so far; ``/api/state?source=S`` the latest
step row of S with its episode's running means; ``/frame.png?source=S`` its latest camera frame.
"""

from __future__ import annotations

import io
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

import numpy as np
from PIL import Image

log = logging.getLogger(__name__)

PAGE = Path(__file__).with_name("live_view.html")
RUNNING_MEANS = ("A", "D", "S_D", "S_A")  # per-step terms whose episode mean is the SPEC's metric
VERTICAL_MEANS = ("E", "S_H")  # and the 3d task's, in its rows only


@dataclass
class LiveSettings:
    """`swimm eval`'s live view (the flags ``--live-*``)."""

    port: int = -1  # serve the live view on this port (0: any free port; -1: no live view)
    host: str = "127.0.0.1"
    env: list[str] = field(default_factory=list)  # also show envs others drive, e.g. train/0 (needs a live view)


@dataclass
class _Source:
    row: dict[str, Any] = field(default_factory=dict)
    image: np.ndarray | None = None
    frame: int = 0  # steps seen; the page asks for a new PNG only when it changes
    steps: int = 0  # steps seen in the current episode (a viewer may join mid-episode)
    sums: dict[str, float] = field(default_factory=dict)
    violations: dict[str, bool] = field(default_factory=dict)
    png: tuple[int, bytes] | None = None  # (frame, encoded) cache


class LiveFeed:
    """Latest step of each watched environment, shared between the step loop and the web server's threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sources: dict[str, _Source] = {}

    def update(self, source: str, row: dict[str, Any], image: np.ndarray | None = None) -> None:
        """Record one step row (evaluator.STEP_FIELDS) of ``source``; running means restart with each episode."""
        with self._lock:
            state = self._sources.setdefault(source, _Source())
            if state.row.get("episode") != row.get("episode") or state.row.get("label") != row.get("label"):
                means = [name for name in RUNNING_MEANS + VERTICAL_MEANS if name in row]
                state.sums, state.steps = dict.fromkeys(means, 0.0), 0
                state.violations = {"left_view": False, "distance_exceeded": False, "collided": False}
            for name in state.sums:
                state.sums[name] += float(row[name])
            state.violations["left_view"] |= not row["in_frustum"]
            state.violations["distance_exceeded"] |= bool(row["distance_exceeded"])
            state.violations["collided"] |= bool(row["collided"])
            state.row = row
            state.frame += 1
            state.steps += 1
            if image is not None:
                state.image = image

    def sources(self) -> list[str]:
        with self._lock:
            return list(self._sources)

    def state(self, source: str) -> dict[str, Any] | None:
        """The latest row, the episode's running metrics (over the steps seen) and the frame counter; None for an
        unknown source."""
        with self._lock:
            state = self._sources.get(source)
            if state is None:
                return None
            episode = {name: total / state.steps for name, total in state.sums.items()} | state.violations
            episode["steps"] = state.steps
            return {"source": source, "frame": state.frame, "has_image": state.image is not None,
                    "step": _plain(state.row), "episode": episode}  # fmt: skip

    def png(self, source: str) -> bytes | None:
        """The latest frame of ``source`` as PNG (encoded once per frame, whatever the number of viewers)."""
        with self._lock:
            state = self._sources.get(source)
            if state is None or state.image is None:
                return None
            if state.png is None or state.png[0] != state.frame:
                buffer = io.BytesIO()
                Image.fromarray(np.ascontiguousarray(state.image)).save(buffer, format="PNG")
                state.png = (state.frame, buffer.getvalue())
            return state.png[1]


def _plain(row: dict[str, Any]) -> dict[str, Any]:
    """JSON-safe copy of a row (numpy scalars and bools become Python ones)."""
    return {key: value.item() if isinstance(value, np.generic) else value for key, value in row.items()}


def tap_frames(env: Any) -> Callable[[], np.ndarray | None]:
    """A getter of the last camera frame ``env`` observed (None where the world does not render): the tracking
    envs' Gymnasium ``render()`` (render mode rgb_array)."""
    return env.render


class LiveView:
    """The web server: ``start()`` serves on ``host:port`` (port 0 picks one; see ``url``) from a daemon thread."""

    def __init__(self, feed: LiveFeed, host: str = "127.0.0.1", port: int = 0) -> None:
        self.feed = feed
        self._server = ThreadingHTTPServer((host, port), _handler(feed, PAGE.read_bytes()))
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, name="live-view", daemon=True)

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> LiveView:
        self._thread.start()
        log.info("live view at %s", self.url)
        return self

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def _handler(feed: LiveFeed, page: bytes) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            url = urlparse(self.path)
            source = (parse_qs(url.query).get("source") or [""])[0]
            if url.path == "/":
                self._send(200, "text/html; charset=utf-8", page)
            elif url.path == "/api/sources":
                self._json(200, feed.sources())
            elif url.path == "/api/state":
                state = feed.state(source)
                self._json(200, state) if state is not None else self._json(404, {"error": f"no source {source!r}"})
            elif url.path == "/frame.png":
                png = feed.png(source)
                if png is None:
                    self._json(404, {"error": f"no frame of {source!r} yet (does the world render?)"})
                else:
                    self._send(200, "image/png", png)
            else:
                self._json(404, {"error": f"unknown path {url.path}"})

        def _json(self, status: int, body: Any) -> None:
            self._send(status, "application/json", json.dumps(body).encode())

        def _send(self, status: int, content_type: str, body: bytes) -> None:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (http.server's signature)
            log.debug("live view: " + format, *args)

    return Handler
