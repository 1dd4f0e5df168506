"""The learner's end of one remote environment: claim, reset, step, with retries.

A :class:`RemoteEnvLink` sends an action (or a reset) and waits for the
matching reply, identified by (episode, seq). On a timeout it re-sends the
same (episode, seq): the sim answers a repeat from its cache without
stepping, and replies that arrive twice are dropped here. So no step is
lost or applied twice, whatever the network or an encoder does.

In ``cmvae`` mode the reply is the encoder's latent, and the link chooses
which encoder encodes each frame by rendezvous hashing of the env id over
the live encoders; a retry recomputes the choice, which is how load moves
off a dead encoder.
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from services import control
from services.keys import Keys
from services.messages import (
    DIRECT_ROUTE,
    ActionMsg,
    BadMessage,
    DiveMode,
    ErrorMsg,
    LatentMsg,
    ObservationMsg,
)
from services.polling import Inbox, poll_seconds
from services.presence import Roster, choose_route, member_ident
from services.telemetry import Telemetry

log = logging.getLogger(__name__)

SimAction = tuple[float, float, float, float]  # (sway, heave, surge, yaw), as ActionMsg carries it


class StepTimeout(TimeoutError):
    """No reply after every retry; the message names the service that is missing."""


class StepRefused(RuntimeError):
    """The sim refused a step or reset; the message carries its reason."""


@dataclass(frozen=True)
class Reply:
    ep: int
    seq: int
    telemetry: Telemetry
    image: np.ndarray | None  # direct mode
    mu: np.ndarray | None  # cmvae mode
    logvar: np.ndarray | None


def decode_reply(payload: bytes, encoded: bool) -> Reply:
    """A step's reply: the encoder's latent (``encoded``) or the sim's observation; BadMessage if unreadable."""
    if encoded:
        msg = LatentMsg.decode(payload)
        mu, logvar = np.asarray(msg.mu, np.float32), np.asarray(msg.logvar, np.float32)
        return Reply(msg.ep, msg.seq, msg.telemetry, None, mu, logvar)
    obs = ObservationMsg.decode(payload)
    return Reply(obs.ep, obs.seq, obs.telemetry, obs.image, None, None)


def await_reply(
    waiter: Any, inbox: Inbox, accept: Callable[[Any], Any], resend: Callable[[], None], missing: Callable[[], str]
) -> Any:
    """The first item of ``inbox`` that ``accept`` takes, re-sending (``resend``) each time ``waiter``'s
    ``step_timeout_s`` passes without one, up to ``max_retries`` times (counted in ``waiter.retries``); then
    StepTimeout with ``missing()``'s message. A re-send nobody answered is logged and waited out like a lost one; a
    refused one (:class:`services.control.ControlError`, e.g. a restarted sim's "not claimed") is raised."""
    for attempt in range(waiter.max_retries + 1):
        deadline = time.monotonic() + waiter.step_timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                item = inbox.get(remaining)
            except queue.Empty:
                break
            if (reply := accept(item)) is not None:
                return reply
        waiter.retries += 1
        log.warning("%s: no reply within %.1f s (try %d); re-sending", waiter.name, waiter.step_timeout_s, attempt + 1)
        try:
            resend()
        except control.ControlTimeout as exc:
            log.warning("%s: re-send failed: %s", waiter.name, exc)
    raise StepTimeout(missing())


def new_holder_id(role: str) -> str:
    """A claim's holder id; `swimm status` finds the process in it (one row for a learner's train and eval envs)."""
    return member_ident(role)


class RemoteEnvLink:
    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        channel: str,
        env: str,
        holder: str,
        encoded: bool,
        encoders: Roster | None = None,
        step_timeout_s: float = 2.0,
        max_retries: int = 10,
        poll_ms: float = 0.0,
    ) -> None:
        self.session, self.keys = session, keys
        self.channel, self.env, self.holder = channel, env, holder
        self.encoded = encoded
        self.encoders = encoders
        self.step_timeout_s = step_timeout_s
        self.max_retries = max_retries
        self._poll_s = poll_seconds(poll_ms)  # services/polling.py: when polling pays
        self.claimed = False  # set by a granted claim; only then does close() release
        self.siblings: tuple[str, ...] = ()  # set by a vector env: its envs' frames spread evenly over the encoders
        self.ep = 0
        self.seq = 0
        self.duplicates_dropped = 0
        self.retries = 0
        self._replies: Inbox[Reply | ErrorMsg | None] = Inbox(self._poll_s)  # None: an unreadable message
        self._pending: tuple[str, object] | None = None  # what to re-send on a timeout
        reply_key = keys.latent(channel, env) if encoded else keys.obs(channel, env, DIRECT_ROUTE)
        self._subscriber = self._replies.subscribe(session, reply_key, self._read_reply)
        self._err_subscriber = self._replies.subscribe(session, keys.err(channel, env), self._read_error)
        self._publisher = session.declare_publisher(
            keys.action(channel, env), congestion_control=zenoh.CongestionControl.BLOCK
        )

    @property
    def name(self) -> str:
        return f"{self.channel}/{self.env}"

    # --- incoming messages, decoded where the Inbox hands them over -----------------------------
    def _read_reply(self, sample: zenoh.Sample) -> Reply | None:
        try:
            return decode_reply(sample.payload.to_bytes(), self.encoded)
        except BadMessage as exc:
            log.warning("%s: dropped an unreadable reply: %s", self.name, exc)
            return None

    def _read_error(self, sample: zenoh.Sample) -> ErrorMsg | None:
        try:
            return ErrorMsg.decode(sample.payload.to_bytes())
        except BadMessage as exc:
            log.warning("%s: unreadable error message: %s", self.name, exc)
            return None

    # --- control ---------------------------------------------------------------------------------
    def claim(self, timeout_s: float = 5.0) -> dict:
        reply = control.request(
            self.session, self.keys.ctl(self.channel, self.env), "claim", timeout_s, holder=self.holder
        )
        self.claimed = True
        return reply

    def release(self) -> None:
        """Give the env back; a link whose claim was refused holds nothing and sends nothing."""
        if not self.claimed:
            return
        self.claimed = False
        try:
            control.request(self.session, self.keys.ctl(self.channel, self.env), "release", 2.0, holder=self.holder)
        except control.ControlError as exc:
            log.warning("%s: release failed: %s", self.name, exc)

    def _route(self) -> str:
        encoders = self.encoders if self.encoded else None
        return choose_route(encoders, self.name, self.step_timeout_s * self.max_retries, self.siblings)

    # --- stepping ----------------------------------------------------------------------------------
    def send_reset(
        self,
        ep: int,
        seed: int,
        noise: bool | dict | None = None,
        latency: dict | None = None,
        scene: dict | None = None,
    ) -> None:
        """Start episode ``ep``; ``noise`` switches the sim's image noise (on, off, a map of noise settings),
        ``latency`` its camera and control delays (a map of sim_service.latency settings) and ``scene`` its scenery
        (a map of sim_service.scenery settings); None leaves each as it is."""
        self.ep, self.seq = ep, 0
        self._pending = ("reset", (seed, noise, latency, scene))
        try:
            self._send()
        except control.ControlTimeout as exc:  # a busy or restarting sim: wait() re-sends it, like a step
            log.warning("%s: reset unanswered (%s); will retry", self.name, exc)

    def send_action(self, action: SimAction, dive_mode: DiveMode = DiveMode.DEPTH_HOLD) -> None:
        self.stage_action(action, dive_mode)
        self._send()

    def stage_action(self, action: SimAction, dive_mode: DiveMode = DiveMode.DEPTH_HOLD) -> None:
        """The next step's action, to be sent by a :class:`learner_service.group_link.GroupLink` with its group's."""
        self.seq += 1
        self._pending = ("action", (action, dive_mode))

    def action_message(self, route: str) -> ActionMsg:
        """The staged action as it goes out, to ``route`` (the same (ep, seq) each time: a retry is a repeat)."""
        if self._pending is None or self._pending[0] != "action":
            raise RuntimeError(f"{self.name}: no action staged")
        action, dive_mode = self._pending[1]
        return ActionMsg(ep=self.ep, seq=self.seq, action=action, dive_mode=dive_mode, route=route, sender=self.holder)

    def _send(self) -> None:
        assert self._pending is not None
        kind, args = self._pending
        route = self._route()
        if kind == "reset":
            seed, noise, latency, scene = args
            world_fields = {key: value for key, value in (("noise", noise), ("latency", latency), ("scene", scene))
                            if value is not None}  # fmt: skip
            control.request(
                self.session,
                self.keys.ctl(self.channel, self.env),
                "reset",
                self.step_timeout_s,
                holder=self.holder,
                ep=self.ep,
                seed=seed,
                route=route,
                **world_fields,
            )
        else:
            self._publisher.put(self.action_message(route).encode())

    def wait(self) -> Reply:
        """The reply to the last send; re-sends the same (ep, seq) on each timeout."""
        return await_reply(self, self._replies, self._accept, self._send, self._missing_service_message)

    def _accept(self, item: Reply | ErrorMsg | None) -> Reply | None:
        """``item`` if it answers the step in flight; raises StepRefused for a refusal of it; else None."""
        if item is None:
            return None
        if isinstance(item, ErrorMsg):
            # Addressed to us (the sim's refusals) or to whoever drives the env (an encoder's).
            if item.sender in (self.holder, "") and (item.ep, item.seq) == (self.ep, self.seq):
                raise StepRefused(f"{self.name}: {item.reason}")
            return None
        if (item.ep, item.seq) == (self.ep, self.seq):
            return item
        self.duplicates_dropped += 1  # a late or repeated reply to an earlier step
        return None

    def _missing_service_message(self) -> str:
        where = f"{self.name} episode {self.ep} seq {self.seq}"
        waited = f"{self.max_retries + 1} tries of {self.step_timeout_s:.1f} s"
        if self.encoded and self.encoders is not None:
            live = sorted(self.encoders.members())
            return (
                f"no latent for {where} after {waited}; live encoders: {live or 'none'}. "
                "Are `swimm sim` and `swimm encoder` running and connected to the same router and namespace?"
            )
        return f"no observation for {where} after {waited}. Is `swimm sim` running and connected?"

    def close(self) -> None:
        self.release()
        self._subscriber.undeclare()
        self._err_subscriber.undeclare()
        self._publisher.undeclare()
