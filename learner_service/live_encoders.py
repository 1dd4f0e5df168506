"""Every live encoder must run the policy's CMVAE: the identity check over Zenoh.

Over Zenoh the latents come from whichever encoder the learner routes to, so `swimm learn` and `swimm eval` ask
each live encoder which CMVAE it runs (`services.presence.ask_about`) and refuse a mismatch by name. Apart from
learner_service.identity so that export and pilot, which only read a checkpoint, do not import Zenoh.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from services.keys import Keys
from services.presence import Roster, ask_about
from services.results import file_sha256

log = logging.getLogger(__name__)


def check_live_encoders(answers: dict[str, dict], expected: str | Path, reader: str) -> None:
    """Refuse when a live encoder (``answers``: its id to what it says it runs, `services.presence.ask_about`)
    runs another CMVAE than ``expected``, the one ``reader`` (a policy, or a run about to record one) reads.

    Over Zenoh the latents come from whichever encoder the learner routes to, so every live one must run it.
    """
    if not answers:
        log.warning("no live encoder said which CMVAE it runs; expecting %s", expected)
        return
    want = file_sha256(expected)
    others = {ident: about for ident, about in answers.items() if about.get("sha256") != want}
    if others:
        named = ", ".join(f"{ident} runs {about.get('checkpoint')} (sha256 {str(about.get('sha256'))[:12]})"
                          for ident, about in sorted(others.items()))  # fmt: skip
        raise ValueError(
            f"{reader} reads encoder {expected} (sha256 {want[:12]}), but live encoder {named}: start the encoders "
            f"with --checkpoint {expected}, or give --encoder-checkpoint the file they run"
        )
    log.info("every live encoder (%s) runs %s", ", ".join(sorted(answers)), expected)


def require_live_encoders(session: Any, keys: Keys, expected: str | Path, reader: str, timeout_s: float) -> None:
    """Wait for the first live encoder (latents need one), then :func:`check_live_encoders` every one live."""
    roster = Roster(session, keys, "encoder")
    try:
        roster.wait_for(1, timeout_s=timeout_s)
    finally:
        roster.close()
    check_live_encoders(ask_about(session, keys, "encoder"), expected, reader)
