"""Request/reply on ``<ns>/<channel>/<env>/ctl``: claim, release, reset, seed, info.

Both ends live here so the protocol is written once: :func:`request` for
callers, :func:`reply` for the queryable side.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import zenoh

from services.messages import BadMessage, encode_reply, encode_request, unpack

log = logging.getLogger(__name__)
MATCH_POLL_S = 0.005  # how often request() checks whether a responder is reachable yet
CLAIMANT_ROLES = ("learner", "eval")  # the roles whose liveliness the sim watches to lapse claims


class ControlError(RuntimeError):
    """A control request was refused or went unanswered; the message says which and why."""


class ControlTimeout(ControlError):
    """Nobody answered a control request in time: worth retrying, unlike a refusal."""


ZENOH_TIMEOUT = "Timeout"  # the error reply Zenoh delivers when a query's timeout passes before its responder replies


def request(session: zenoh.Session, key: str, op: str, timeout_s: float = 5.0, **args: Any) -> dict[str, Any]:
    """Send one control request to exactly one responder and return its reply map.

    Raises :class:`ControlError` with the responder's reason on refusal, or
    naming the key when nobody answered within ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    querier = session.declare_querier(key, timeout=timeout_s)
    try:
        # A query sent before the responder's route reached this session gets no reply at all; wait (bounded) for it.
        while not querier.matching_status.matching and time.monotonic() < deadline:
            time.sleep(MATCH_POLL_S)
        replies = list(querier.get(payload=encode_request(op, **args)))
    finally:
        querier.undeclare()
    for reply in replies:
        if reply.ok is None:
            reason = reply.err.payload.to_bytes().decode(errors="replace")
            if reason == ZENOH_TIMEOUT:  # a responder that was too slow: as retryable as no responder at all
                break
            raise ControlError(f"{op} on {key} failed: {reason}")
        try:
            body = unpack(reply.ok.payload.to_bytes())
        except BadMessage as exc:
            raise ControlError(f"{op} on {key}: unreadable reply ({exc})") from None
        if not body.get("ok"):
            raise ControlError(f"{op} on {key} refused: {body.get('error', 'no reason given')}")
        return body
    raise ControlTimeout(f"{op} on {key}: no reply within {timeout_s:.1f} s; is `swimm sim` running with this env?")


def survey(session: zenoh.Session, key: str, timeout_s: float = 3.0) -> list[dict[str, Any]]:
    """Ask every responder matching a wildcard key for its ``info`` (discovery of live envs)."""
    found = []
    # Without NONE, Zenoh merges replies that share a key expression, and each env answers on the query's key.
    replies = session.get(
        key, payload=encode_request("info"), timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            body = unpack(reply.ok.payload.to_bytes())
        except BadMessage:
            continue
        if body.get("ok"):
            found.append(body)
    return found


def reply(query: zenoh.Query, ok: bool, **fields: Any) -> None:
    """Answer a query and release it at once, so the caller is not left waiting for its timeout."""
    try:
        query.reply(query.key_expr, encode_reply(ok, **fields))
    finally:
        query.drop()
