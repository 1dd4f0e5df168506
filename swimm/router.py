"""`swimm router`: a Zenoh router in a Python process (:class:`services.router.Router`), until signalled."""

from __future__ import annotations

from services.lifecycle import serve_until_signalled
from services.router import Router, RouterSettings


def run(settings: RouterSettings) -> None:
    serve_until_signalled(Router(settings))
