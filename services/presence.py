"""Liveliness: every service announces itself, and others watch who is alive.

A token lives as long as its session, so a crashed process disappears from
``<ns>/@live/<role>/*`` without saying goodbye; that is how claims lapse and
how encoder load moves away from a dead encoder.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import re
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from types import MappingProxyType

import zenoh

from services.keys import Keys
from services.lifecycle import Owner
from services.messages import DIRECT_ROUTE

log = logging.getLogger(__name__)


#: This process's tag, in the id of every member it announces (a learner claims its train and eval envs as two).
PROCESS_TAG = uuid.uuid4().hex[:8]
_MEMBER = re.compile(r"(.+-[0-9a-f]{8})-[0-9a-f]{6}")


def process_ident(role: str) -> str:
    """This process's id in ``role``: what its metrics carry, and how each of its member ids begins."""
    return f"{role}-{PROCESS_TAG}"


def member_ident(role: str) -> str:
    """A new id for one of several members of this process: ``<role>-<process tag>-<member>``."""
    return f"{process_ident(role)}-{uuid.uuid4().hex[:6]}"


def process_of(ident: str) -> str:
    """The process a member id belongs to (``learner-1a2b3c4d-5e6f70``: ``learner-1a2b3c4d``); any other id is a
    process of its own (``sim-0``)."""
    match = _MEMBER.fullmatch(ident)
    return match.group(1) if match else ident


def announce(session: zenoh.Session, keys: Keys, role: str, ident: str) -> zenoh.LivelinessToken:
    """Declare this service's token; keep the returned object referenced or it is undeclared."""
    return session.liveliness().declare_token(keys.live(role, ident))


def declare_about(session: zenoh.Session, keys: Keys, role: str, ident: str, about: dict) -> zenoh.Queryable:
    """Answer queries for what this service runs with ``about`` (JSON); keep the returned object referenced."""
    key, payload = keys.about(role, ident), json.dumps(about)
    return session.declare_queryable(key, lambda query: query.reply(key, payload))  # its own key names it


def ask_about(session: zenoh.Session, keys: Keys, role: str, timeout_s: float = 2.0) -> dict[str, dict]:
    """What every live member of ``role`` that answers says it runs, by id."""
    answers = {}
    for reply in session.get(keys.about_role(role), timeout=timeout_s):
        if reply.ok is not None:
            answers[str(reply.ok.key_expr).rsplit("/", 1)[-1]] = json.loads(reply.ok.payload.to_bytes())
    return answers


def live_now(session: zenoh.Session, keys: Keys, role: str, timeout_s: float = 2.0) -> set[str]:
    """The members of ``role`` whose tokens the network holds right now, asked afresh.

    A :class:`Roster` can keep a stale arrival (its history reply may land after the departure it
    predates), so decisions that free resources ask again here.
    """
    return {ident for _, ident in live_tokens(session, keys.live_role(role), timeout_s)}


def live_tokens(session: zenoh.Session, key_expr: str, timeout_s: float = 2.0) -> set[tuple[str, str]]:
    """(role, id) of every liveliness token matching ``key_expr`` that the network holds now."""
    tokens = set()
    for reply in session.liveliness().get(key_expr, timeout=timeout_s):
        if reply.ok is not None:
            role, ident = str(reply.ok.key_expr).split("/")[-2:]
            tokens.add((role, ident))
    return tokens


class Roster(Owner):
    """The live members of one role, kept current by a liveliness subscriber.

    ``on_change(joined, left)`` runs on a Zenoh thread after each change, so
    it must be quick.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        role: str,
        on_change: Callable[[set[str], set[str]], None] | None = None,
    ) -> None:
        self._members: set[str] = set()
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._on_change = on_change
        self.role = role
        self.resources.enter_context(
            session.liveliness().declare_subscriber(keys.live_role(role), self._on_sample, history=True)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        ident = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                joined, left = ({ident} - self._members), set()
                self._members.add(ident)
            else:  # reported even when its arrival was never seen: the token may have raced a claim
                joined, left = set(), {ident}
                self._members.discard(ident)
            self._changed.notify_all()
        if joined or left:
            log.info("%s roster: joined %s left %s", self.role, sorted(joined), sorted(left))
            if self._on_change:
                self._on_change(joined, left)

    def members(self) -> set[str]:
        with self._lock:
            return set(self._members)

    def wait_for(self, count: int = 1, timeout_s: float = 30.0) -> set[str]:
        """Block until at least ``count`` members are live; raise TimeoutError naming the role otherwise."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while len(self._members) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f"no live {self.role} after {timeout_s:.0f} s (need {count}, see {len(self._members)}); "
                        f"is `swimm {self.role}` running and connected to the same router and namespace?"
                    )
                self._changed.wait(remaining)
            return set(self._members)


def _score(key: str, member: str) -> bytes:
    return hashlib.blake2b(f"{key}|{member}".encode(), digest_size=8).digest()


def rendezvous_choice(env_key: str, members: set[str]) -> str:
    """The member with the highest hash for this env: stable, and only the dead member's envs move."""
    return max(members, key=lambda m: _score(env_key, m))


def balanced_choice(key: str, siblings: Sequence[str], members: set[str]) -> str:
    """Rendezvous hashing with bounded load over one sender's ``siblings`` (``key`` among them): in sorted order,
    each takes its highest-hashing member that holds fewer than the even share (siblings over members, rounded
    down), then the rest take theirs among the members holding no more than that, so loads differ by one at most.

    Plain rendezvous hashing puts two groups on one of two encoders half the time, and the groups of a vector step
    then queue at one encoder while the other idles; this spreads one learner's groups evenly, as stably.
    """
    if key not in siblings:
        raise ValueError(f"{key!r} is not among its siblings {sorted(siblings)}")
    return _balanced_routes(frozenset(siblings), frozenset(members))[key]


@functools.lru_cache(maxsize=64)
def _balanced_routes(siblings: frozenset[str], members: frozenset[str]) -> MappingProxyType[str, str]:
    """Every sibling's member, worked out once per membership: each group's send asks again every step."""
    even_share = len(siblings) // len(members)
    load = dict.fromkeys(members, 0)
    chosen: dict[str, str] = {}
    for cap in (even_share, even_share + 1):
        for sibling in sorted(siblings - chosen.keys()):
            ranked = sorted(members, key=lambda m: _score(sibling, m), reverse=True)
            room = [member for member in ranked if load[member] < cap]
            if room:
                chosen[sibling] = room[0]
                load[room[0]] += 1
    return MappingProxyType(chosen)


def choose_route(encoders: Roster | None, key: str, wait_s: float, siblings: Sequence[str] = ()) -> str:
    """Where a step's observation goes: ``direct`` without encoders, else the live encoder rendezvous hashing
    picks for ``key`` (waiting up to ``wait_s`` for one to come back if none is live), balanced over
    ``siblings`` when given (:func:`balanced_choice`)."""
    if encoders is None:
        return DIRECT_ROUTE
    members = encoders.members() or encoders.wait_for(1, timeout_s=wait_s)
    if siblings:
        return balanced_choice(key, siblings, members)
    return rendezvous_choice(key, members)
