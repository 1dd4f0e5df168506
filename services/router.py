"""A Zenoh router in a Python process, so no extra binary is needed (`swimm router`: swimm/router.py)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from services.lifecycle import Service
from services.session import open_session
from services.settings import LOCAL_ROUTER, NonNegInt, ZenohSettings

log = logging.getLogger(__name__)


@dataclass
class RouterSettings:
    listen: list[str] = field(
        default_factory=list,
        metadata={"help": f"endpoints to listen on; none: the --zenoh-config file's, else {LOCAL_ROUTER}"},
    )
    connect: list[str] = field(default_factory=list)  # other routers, for multi-site set-ups
    zenoh_config: str | None = None  # e.g. deploy/zenoh/router-tls-acl.json5
    low_latency: bool = False  # lock-step Zenoh, as ZenohSettings.low_latency: with the clients and peers that ask too
    zenoh_threads: NonNegInt = 0  # Zenoh's worker threads; 0: Zenoh's pools (on one thread, cut links were seen late)

    def zenoh(self) -> ZenohSettings:
        """The session settings the router opens with: router mode, connecting only where told to."""
        return ZenohSettings(mode="router", connect=self.connect, listen=self.listen, zenoh_config=self.zenoh_config,
                             startup_timeout_s=10.0, low_latency=self.low_latency,
                             zenoh_threads=self.zenoh_threads)  # fmt: skip


class Router(Service):
    def __init__(self, settings: RouterSettings) -> None:
        self.settings = settings

    def start(self) -> None:
        self.session = self.resources.enter_context(open_session(self.settings.zenoh(), role="router"))
        log.info("router %s up", self.session.zid())

    def close(self) -> None:
        super().close()
        log.info("router stopped")
