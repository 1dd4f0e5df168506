#!/usr/bin/env python3
"""Container health from liveliness: healthy while this container's service holds its token on the router.

A service's liveliness token lives exactly as long as its Zenoh session, so "my token is visible through
the router" means: the process runs, it reached the router, and the router still routes for it. That is
the health that matters for the step pipeline, where an open port or a running process would not be.

Configured by environment variables (installed in the images as ``swimm-health``):
  SWIMM_HEALTH_ROLE   router | sim | encoder | learner | eval (default router)
  SWIMM_HEALTH_IDENT  the token's id; "{hostname}" is replaced by the container's host name, so scaled
                      replicas each check their own (e.g. "enc-{hostname}"); default "*" (any of the role)
  SWIMM_HEALTH_PORT   router only: the port it listens on (default 7447)
and the service's own SWIMM_CONNECT, SWIMM_NAMESPACE, SWIMM_ZENOH_CONFIG. Exit status 0 = healthy.
"""

from __future__ import annotations

import os
import socket
import sys

from services.keys import Keys
from services.session import open_session
from services.settings import ZenohSettings, load


def router_listens(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=3):
            return True
    except OSError:
        return False


def token_visible(role: str, ident: str) -> bool:
    settings = load(ZenohSettings)
    settings.startup_timeout_s = 3.0
    with open_session(settings, role="health") as session:
        replies = session.liveliness().get(Keys(settings.namespace).live(role, ident), timeout=3.0)
        return any(reply.ok is not None for reply in replies)


def main() -> int:
    role = os.environ.get("SWIMM_HEALTH_ROLE", "router")
    if role == "router":
        return 0 if router_listens(int(os.environ.get("SWIMM_HEALTH_PORT", "7447"))) else 1
    ident = os.environ.get("SWIMM_HEALTH_IDENT", "*").replace("{hostname}", socket.gethostname())
    try:
        healthy = token_visible(role, ident)
    except Exception as exc:  # no router, bad config: unhealthy, with the reason in `docker inspect`
        print(f"unhealthy: {exc}", file=sys.stderr)
        return 1
    print(f"{role} {ident}: {'live' if healthy else 'no liveliness token'}")
    return 0 if healthy else 1


if __name__ == "__main__":
    sys.exit(main())
