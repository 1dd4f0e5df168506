"""One logging format for every service: time, role, level, message."""

from __future__ import annotations

import logging
import os


def setup_logging(role: str, level: str | None = None) -> None:
    level = (level or os.environ.get("SWIMM_LOG_LEVEL", "INFO")).upper()
    logging.basicConfig(
        level=level,
        format=f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s",
        force=True,
    )
