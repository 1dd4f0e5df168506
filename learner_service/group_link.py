"""The learner's end of a group of remote environments, stepped as one message each way.

A :class:`GroupLink` sends the actions of its envs in one :class:`services.messages.BatchMsg`; the sim steps
them in order and answers with one message of observations, which one encoder turns into one message of
latents (one forward pass). The per-env guarantees of :class:`learner_service.link.RemoteEnvLink` hold item by
item: each action keeps its env's (episode, seq), a timeout re-sends the same items (the sim answers repeats from
its cache without stepping), a reply to an earlier step is dropped, and each re-send routes the group anew over
the live encoders, which is how a group moves off a dead one. Claims and resets stay per env, on each env's link.
"""

from __future__ import annotations

import logging

import zenoh

from learner_service.link import RemoteEnvLink, Reply, SimAction, StepRefused, await_reply, decode_reply
from services.keys import GROUPS, Keys
from services.messages import DIRECT_ROUTE, BadMessage, BatchItem, BatchMsg
from services.polling import Inbox, poll_seconds
from services.presence import choose_route

log = logging.getLogger(__name__)


class GroupLink:
    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        group: str,
        links: list[RemoteEnvLink],
        poll_ms: float = 0.0,
    ) -> None:
        if not links:
            raise ValueError("a group needs at least one env")
        first = links[0]
        self.channel, self.group, self.links = first.channel, group, links
        self.holder, self.encoded, self.encoders = first.holder, first.encoded, first.encoders
        self.step_timeout_s, self.max_retries = first.step_timeout_s, first.max_retries
        # The names of every group its learner steps (this one's included), over which encoders are shared evenly
        # (services.presence.balanced_choice); empty: this group's own rendezvous choice.
        self.siblings: tuple[str, ...] = ()
        self.retries = 0
        self.duplicates_dropped = 0
        self._replies: Inbox[BatchMsg | None] = Inbox(poll_seconds(poll_ms))
        if self.encoded:
            reply_key = keys.group_latent(self.channel, group)
        else:
            reply_key = keys.group_obs(self.channel, group, DIRECT_ROUTE)
        self._subscriber = self._replies.subscribe(session, reply_key, self._read)
        self._publisher = session.declare_publisher(
            keys.group_action(self.channel, group), congestion_control=zenoh.CongestionControl.BLOCK
        )

    @property
    def name(self) -> str:
        return f"{self.channel}/{GROUPS}/{self.group}"

    def _read(self, sample: zenoh.Sample) -> BatchMsg | None:
        try:
            return BatchMsg.decode(sample.payload.to_bytes())
        except BadMessage as exc:
            log.warning("%s: dropped an unreadable reply: %s", self.name, exc)
            return None

    def send(self, actions: list[SimAction]) -> None:
        """Stage one action per env (in the group's order) and send them together."""
        if len(actions) != len(self.links):
            raise ValueError(f"{self.name}: {len(actions)} actions for {len(self.links)} envs")
        for link, action in zip(self.links, actions, strict=True):
            link.stage_action(action)
        self._send()

    def _send(self) -> None:
        encoders = self.encoders if self.encoded else None
        route = choose_route(encoders, self.name, self.step_timeout_s * self.max_retries, self.siblings)
        items = tuple(
            BatchItem(link.env, link.ep, link.seq, link.action_message(route).encode()) for link in self.links
        )
        self._publisher.put(BatchMsg(self.group, self.holder, items).encode())

    def wait(self) -> list[Reply]:
        """The replies to the last send, in the group's order; re-sends the same steps on each timeout."""
        return await_reply(self, self._replies, self._match, self._send, self._missing_service_message)

    def _missing_service_message(self) -> str:
        services = "`swimm sim` and `swimm encoder`" if self.encoded else "`swimm sim`"
        return (
            f"no reply for group {self.name} ({len(self.links)} envs) after {self.max_retries + 1} tries of "
            f"{self.step_timeout_s:.1f} s. Are {services} running and connected to the same router and namespace?"
        )

    def _match(self, batch: BatchMsg | None) -> list[Reply] | None:
        """The replies if ``batch`` answers the steps in flight; None (and counted) for an answer to earlier ones."""
        if batch is None:
            return None
        expected = [(link.env, link.ep, link.seq) for link in self.links]
        if [(item.env, item.ep, item.seq) for item in batch.items] != expected:
            self.duplicates_dropped += 1
            return None
        replies = []
        for link, item in zip(self.links, batch.items, strict=True):
            if item.error:
                raise StepRefused(f"{link.name}: {item.error}")
            try:
                replies.append(decode_reply(item.payload, self.encoded))
            except BadMessage as exc:
                log.warning("%s: unreadable reply for %s: %s; waiting for a re-send", self.name, link.name, exc)
                return None
        return replies

    def close(self) -> None:
        self._subscriber.undeclare()
        self._publisher.undeclare()
