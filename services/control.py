"""Request/reply on ``<ns>/<channel>/<env>/ctl``: claim, release, reset, info.

Both ends live here so the protocol is written once: :func:`request` for
callers, :func:`reply` for the queryable side. The messages are the typed
control messages of services/messages.py.
"""

from __future__ import annotations

import logging

import zenoh

from services.messages import (
    BadMessage,
    ControlRequest,
    EnvState,
    InfoReply,
    InfoRequest,
    Refused,
    decode_reply,
)
from services.session import wait_for_matching

log = logging.getLogger(__name__)
CLAIMANT_ROLES = ("learner", "eval")  # the roles whose liveliness the sim watches to lapse claims


class ControlError(RuntimeError):
    """A control request was refused or went unanswered; the message says which and why."""


class ControlTimeout(ControlError):
    """Nobody answered a control request in time: worth retrying, unlike a refusal."""


ZENOH_TIMEOUT = "Timeout"  # the error reply Zenoh delivers when a query's timeout passes before its responder replies


def request(session: zenoh.Session, key: str, message: ControlRequest, timeout_s: float = 5.0) -> EnvState:
    """Send one control request to exactly one responder and return its granted reply (``message.REPLY``).

    Raises :class:`ControlError` with the responder's reason on refusal, or
    naming the key when nobody answered within ``timeout_s``.
    """
    op = message.OP
    querier = session.declare_querier(key, timeout=timeout_s)
    try:
        wait_for_matching([querier], timeout_s)  # a query sent before the responder's route arrived gets no reply
        replies = list(querier.get(payload=message.encode()))
    finally:
        querier.undeclare()
    for reply in replies:
        if reply.ok is None:
            reason = reply.err.payload.to_bytes().decode(errors="replace")
            if reason == ZENOH_TIMEOUT:  # a responder that was too slow: as retryable as no responder at all
                break
            raise ControlError(f"{op} on {key} failed: {reason}")
        try:
            answer = decode_reply(reply.ok.payload.to_bytes(), message.REPLY)
        except BadMessage as exc:
            raise ControlError(f"{op} on {key}: unreadable reply ({exc})") from None
        if isinstance(answer, Refused):
            raise ControlError(f"{op} on {key} refused: {answer.reason}")
        return answer
    raise ControlTimeout(f"{op} on {key}: no reply within {timeout_s:.1f} s; is `swimm sim` running with this env?")


def survey(session: zenoh.Session, key: str, timeout_s: float = 3.0) -> list[InfoReply]:
    """Ask every responder matching a wildcard key for its ``info`` (discovery of live envs); refusals and
    unreadable replies are left out."""
    found = []
    # Without NONE, Zenoh merges replies that share a key expression, and each env answers on the query's key.
    replies = session.get(
        key, payload=InfoRequest().encode(), timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            answer = decode_reply(reply.ok.payload.to_bytes(), InfoReply)
        except BadMessage:
            continue
        if isinstance(answer, InfoReply):
            found.append(answer)
    return found


def reply(query: zenoh.Query, answer: EnvState | Refused) -> None:
    """Answer a query and release it at once, so the caller is not left waiting for its timeout."""
    try:
        query.reply(query.key_expr, answer.encode())
    finally:
        query.drop()
