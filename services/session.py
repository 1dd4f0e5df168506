"""Opening Zenoh sessions: clients, peers and the router, with a bounded, logged wait.

A client-mode session fails at open when no router answers, so services
retry with back-off until ``startup_timeout_s``; that is what lets them
start in any order. Multicast scouting is off: endpoints are explicit, so
two runs on one machine never see each other by accident.

Peers still find each other through the router they connect to (Zenoh's gossip) and then link directly, so a
message between two peers skips the router's hop. A peer with no listen endpoint of its own listens on
:data:`PEER_LISTEN`, a loopback port, which reaches the peers on its machine; peers on other machines are
then introduced but cannot link, and their messages go through the router as a client's do.
"""

from __future__ import annotations

import json
import logging
import re
import time

import zenoh

from services.settings import LOCAL_ROUTER, ZenohSettings

log = logging.getLogger(__name__)
PEER_LISTEN = "tcp/127.0.0.1:0"  # a peer's own listener when none is given: any free loopback port
#: The largest message a low-latency session may send. That transport does not fragment: a message must fit
#: one 49,152-byte batch with its headers, and one that does not is lost together with the link's later
#: messages (docs/benchmarks.md, the low-latency transport). Services that send large messages check theirs
#: against this before they start.
LOW_LATENCY_MAX_MESSAGE_BYTES = 48_000


class StartupTimeout(RuntimeError):
    """No peer or router could be reached within the startup timeout."""


def build_config(settings: ZenohSettings) -> zenoh.Config:
    """The Zenoh config: the file's (if any), then the settings' endpoints over it.

    Endpoints come from the flags when given, else from the config file when it names any, else a
    router listens on (and the others connect to) :data:`LOCAL_ROUTER` and a peer listens on :data:`PEER_LISTEN`.
    """
    config = zenoh.Config.from_file(settings.zenoh_config) if settings.zenoh_config else zenoh.Config()
    stock = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    for key, given, local_default in (
        ("connect/endpoints", settings.connect, LOCAL_ROUTER if settings.mode != "router" else None),
        ("listen/endpoints", settings.listen, {"router": LOCAL_ROUTER, "peer": PEER_LISTEN}.get(settings.mode)),
    ):
        endpoints = list(given)
        if not endpoints and local_default and config.get_json(key) == stock.get_json(key):
            endpoints = [local_default]
        if endpoints:
            config.insert_json5(key, json.dumps(endpoints))
    if not settings.zenoh_config:
        config.insert_json5("scouting/multicast/enabled", "false")
    if settings.low_latency:
        use_low_latency_transport(config)
    if settings.mode != "router":
        # Keep retrying the router forever once running, so a restarted router is rejoined.
        config.insert_json5("connect/timeout_ms", "-1" if settings.mode == "peer" else "0")
    return config


def use_low_latency_transport(config: zenoh.Config) -> None:
    """Ask for Zenoh's low-latency transport on every link whose other end asks for it too.

    The standard transport hands each message to a batching task on another thread; the low-latency one
    writes it to the socket from the sending thread, which takes a thread hand-over off each hop. It cannot
    fragment (:data:`LOW_LATENCY_MAX_MESSAGE_BYTES`) and does not keep QoS priorities, which Zenoh requires to
    be switched off with it. Two such peers that dial each other at the same moment can break both links for
    good, so only the peer with the greater Zenoh id dials the other. Shared memory (Zenoh's default for
    messages over 3 KB between processes of one machine) is switched off too: over this transport it made the
    observation's round trip slower. docs/benchmarks.md (the low-latency transport) has the numbers.
    """
    config.insert_json5("transport/unicast/lowlatency", "true")
    config.insert_json5("transport/unicast/qos/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    config.insert_json5(
        "scouting/gossip/autoconnect_strategy", json.dumps({"peer": {"to_router": "always", "to_peer": "greater-zid"}})
    )


def endpoints(config: zenoh.Config, direction: str = "connect") -> list[str] | dict[str, list[str]]:
    """The endpoints a config will ``connect`` to or ``listen`` on (a list, or a map per mode), for messages."""
    return json.loads(config.get_json(f"{direction}/endpoints"))


def describe_endpoints(config: zenoh.Config, direction: str = "connect", mode: str | None = None) -> str:
    """``endpoints`` as a person reads it in a log line or an error: comma-separated, per mode where mapped, or
    only ``mode``'s (Zenoh's stock config maps a router's listener, which a client never opens)."""
    found = endpoints(config, direction)
    if isinstance(found, dict) and mode is not None:
        found = found.get(mode, [])
    if isinstance(found, dict):
        return "; ".join(f"{mode}: {', '.join(items)}" for mode, items in found.items()) or "none"
    return ", ".join(found) or "none"


def zenoh_reason(exc: Exception) -> str:
    """Zenoh's error without the Rust source location it ends with (``at /root/.cargo/.../orchestrator.rs:447.``)."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).rstrip(" .!") or type(exc).__name__


def open_session(settings: ZenohSettings, role: str = "service") -> zenoh.Session:
    """Open a session, retrying with back-off until ``settings.startup_timeout_s``.

    ``settings.zenoh_threads`` is the process's, not the session's: Zenoh reads its thread pools once, when the
    process opens its first session, from ``ZENOH_RUNTIME``, which the entry point sets
    (services/process.py, :func:`~services.process.configure_process`). Here it is only checked.
    """
    if settings.zenoh_threads < 0:
        raise ValueError(f"--zenoh-threads must be >= 0 (0: Zenoh's pool per runtime), got {settings.zenoh_threads}")
    try:
        config = build_config(settings)  # a bad config file is the user's to fix: fail at once, not after retries
    except zenoh.ZError as exc:
        raise ValueError(f"cannot use Zenoh config {settings.zenoh_config!r}: {exc}") from None
    deadline = time.monotonic() + settings.startup_timeout_s
    delay = 0.1
    attempt = 0
    while True:
        attempt += 1
        try:
            session = zenoh.open(config)
            log.info(
                "%s joined Zenoh as %s (connect=%s listen=%s%s)",
                role,
                settings.mode,
                describe_endpoints(config),
                describe_endpoints(config, "listen", settings.mode),
                ", low-latency transport" if settings.low_latency else "",
            )
            return session
        except zenoh.ZError as exc:
            if time.monotonic() + delay > deadline:
                raise StartupTimeout(
                    f"{role} could not reach a Zenoh router at {describe_endpoints(config)} within "
                    f"{settings.startup_timeout_s:g} s ({attempt} attempts): {zenoh_reason(exc)}. "
                    "Is `swimm router` (or `swimm up`) running?"
                ) from None
            # One line says what it waits for; the retries after it are for DEBUG logs.
            log.log(logging.INFO if attempt == 1 else logging.DEBUG,
                    "%s waiting up to %g s for a Zenoh router at %s (attempt %d): %s", role,
                    settings.startup_timeout_s, describe_endpoints(config), attempt, zenoh_reason(exc))  # fmt: skip
            time.sleep(delay)
            delay = min(delay * 2, 2.0)


MATCH_POLL_S = 0.005  # how often wait_for_matching checks whether the routes have arrived


def wait_for_matching(entities, timeout_s: float) -> bool:
    """Wait up to ``timeout_s`` until every publisher or querier in ``entities`` has a match; True if all do.

    A new session learns from the router who listens only a moment after it opens: a sample put or a query sent
    before then reaches nobody.
    """
    entities = list(entities)
    deadline = time.monotonic() + timeout_s
    while not all(entity.matching_status.matching for entity in entities):
        if time.monotonic() >= deadline:
            return False
        time.sleep(MATCH_POLL_S)
    return True
