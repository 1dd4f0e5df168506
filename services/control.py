"""Request/reply on ``<ns>/<channel>/<env>/ctl``: claim, release, reset, seed, info.

Both ends live here so the protocol is written once: :func:`request` for
callers, :func:`reply` for the queryable side.
"""

from __future__ import annotations

import logging
from typing import Any

import zenoh

from services.messages import BadMessage, encode_reply, encode_request, unpack

log = logging.getLogger(__name__)


class ControlError(RuntimeError):
    """A control request was refused or went unanswered; the message says which and why."""


def request(session: zenoh.Session, key: str, op: str, timeout_s: float = 5.0, **args: Any) -> dict[str, Any]:
    """Send one control request to exactly one responder and return its reply map.

    Raises :class:`ControlError` with the responder's reason on refusal, or
    naming the key when nobody answered within ``timeout_s``.
    """
    replies = session.get(key, payload=encode_request(op, **args), timeout=timeout_s)
    for reply in replies:
        if reply.ok is None:
            raise ControlError(f"{op} on {key} failed: {reply.err.payload.to_bytes().decode(errors='replace')}")
        try:
            body = unpack(reply.ok.payload.to_bytes())
        except BadMessage as exc:
            raise ControlError(f"{op} on {key}: unreadable reply ({exc})") from None
        if not body.get("ok"):
            raise ControlError(f"{op} on {key} refused: {body.get('error', 'no reason given')}")
        return body
    raise ControlError(f"{op} on {key}: no reply within {timeout_s:.1f} s; is `swimm sim` running with this env?")


def survey(session: zenoh.Session, key: str, timeout_s: float = 3.0) -> list[dict[str, Any]]:
    """Ask every responder matching a wildcard key for its ``info`` (discovery of live envs)."""
    found = []
    for reply in session.get(key, payload=encode_request("info"), timeout=timeout_s):
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
