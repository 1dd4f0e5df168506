"""Running a service until SIGTERM/SIGINT and then draining it."""

from __future__ import annotations

import signal
import threading
from typing import Protocol


class Service(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...


def serve_until_signalled(service: Service, stop_event: threading.Event | None = None) -> None:
    """Start ``service``, block until SIGTERM or SIGINT (or ``stop_event``), then stop it cleanly."""
    stop_event = stop_event or threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop_event.set())
    service.start()
    try:
        stop_event.wait()
    finally:
        service.stop()
