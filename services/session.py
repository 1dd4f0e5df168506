"""Opening Zenoh sessions: clients, peers and the router, with a bounded, logged wait.

A client-mode session fails at open when no router answers, so services
retry with back-off until ``startup_timeout_s``; that is what lets them
start in any order. Multicast scouting is off: endpoints are explicit, so
two runs on one machine never see each other by accident.
"""

from __future__ import annotations

import json
import logging
import time

import zenoh

from services.settings import ZenohSettings

log = logging.getLogger(__name__)


class StartupTimeout(RuntimeError):
    """No peer or router could be reached within the startup timeout."""


def build_config(settings: ZenohSettings) -> zenoh.Config:
    config = zenoh.Config.from_file(settings.zenoh_config) if settings.zenoh_config else zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    if not settings.zenoh_config:
        config.insert_json5("scouting/multicast/enabled", "false")
    if settings.mode != "router":
        # Keep retrying the router forever once running, so a restarted router is rejoined.
        config.insert_json5("connect/timeout_ms", "-1" if settings.mode == "peer" else "0")
    return config


def open_session(settings: ZenohSettings, role: str = "service") -> zenoh.Session:
    """Open a session, retrying with back-off until ``settings.startup_timeout_s``."""
    deadline = time.monotonic() + settings.startup_timeout_s
    delay = 0.1
    attempt = 0
    while True:
        attempt += 1
        try:
            session = zenoh.open(build_config(settings))
            log.info(
                "%s joined Zenoh as %s (connect=%s listen=%s)", role, settings.mode, settings.connect, settings.listen
            )
            return session
        except zenoh.ZError as exc:
            if time.monotonic() + delay > deadline:
                raise StartupTimeout(
                    f"{role} could not reach a Zenoh router at {settings.connect} within "
                    f"{settings.startup_timeout_s:.0f} s ({attempt} attempts): {exc}. Is `swimm router` running?"
                ) from None
            log.info("%s waiting for a Zenoh router at %s (attempt %d): %s", role, settings.connect, attempt, exc)
            time.sleep(delay)
            delay = min(delay * 2, 2.0)


def router_settings(
    listen: list[str], namespace: str = "swimm/default", zenoh_config: str | None = None
) -> ZenohSettings:
    return ZenohSettings(mode="router", connect=[], listen=listen, namespace=namespace, zenoh_config=zenoh_config)
