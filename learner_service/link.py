"""The learner's end of remote environments: claim, reset, step, with retries.

An :class:`EnvLink` steps a group of envs, one message each way (a single env is a group of one): it sends
their actions in one :class:`services.messages.BatchMsg`, the sim steps them in order and answers with one
message of observations, which one encoder turns into one message of latents (one forward pass). A step is
identified per env by (episode, seq). On a timeout the link re-sends the same items: the sim answers a repeat
from its cache without stepping, and replies that arrive twice are dropped here. So no step is lost or applied
twice, whatever the network or an encoder does.

In ``cmvae`` mode the reply is the encoder's latents, and the link chooses which encoder encodes them by
rendezvous hashing of its name over the live encoders; a retry recomputes the choice, which is how load moves
off a dead encoder. A tracking encoder's ``next_prior`` goes back with each env's next action (the sim echoes it
to the encoder), so the encoder keeps no state and a failover loses none. Claims and resets go per env over the
control plane (services/control.py); a reset's observation comes back as its env's group of one.
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import zenoh

from learner_service.task import Frame
from services import control
from services.keys import Keys
from services.messages import (
    DIRECT_ROUTE,
    ActionMsg,
    BadMessage,
    BatchItem,
    BatchMsg,
    ClaimRequest,
    DiveMode,
    EnvState,
    LatentMsg,
    ObservationMsg,
    Prior,
    ReleaseRequest,
    ResetRequest,
)
from services.polling import Inbox, poll_seconds
from services.presence import Roster, choose_route, member_ident

log = logging.getLogger(__name__)

SimAction = tuple[float, float, float, float]  # (sway, heave, surge, yaw), as ActionMsg carries it


class StepTimeout(TimeoutError):
    """No reply after every retry; the message names the service that is missing."""


class StepRefused(RuntimeError):
    """The sim refused a step or reset; the message carries its reason."""


def decode_reply(item: BatchItem, encoded: bool) -> tuple[Frame, Prior | None]:
    """One env's reply: the encoder's latent (``encoded``) or the sim's observation, with the prior for the env's
    next action (a tracking encoder's ``next_prior``, else None); BadMessage if unreadable."""
    if encoded:
        msg = LatentMsg.from_item(item)
        mu, logvar = np.asarray(msg.mu, np.float32), np.asarray(msg.logvar, np.float32)
        return Frame(msg.telemetry, mu=mu, logvar=logvar), msg.next_prior
    obs = ObservationMsg.from_item(item)
    return Frame(obs.telemetry, image=obs.image), None


def new_holder_id(role: str) -> str:
    """A claim's holder id; `swimm status` finds the process in it (one row for a learner's train and eval envs)."""
    return member_ident(role)


class EnvLink:
    """The learner's end of ``envs`` (one or several) on ``channel``, stepped as group ``group`` (default and for one
    env: the env's id). ``ep``, ``seq``, ``priors`` and ``claimed`` are per env, in the link's order."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        channel: str,
        envs: Sequence[str],
        holder: str,
        encoded: bool,
        encoders: Roster | None = None,
        step_timeout_s: float = 2.0,
        max_retries: int = 10,
        poll_ms: float = 0.0,
        group: str = "",
    ) -> None:
        if not envs:
            raise ValueError("a link needs at least one env")
        if not group and len(envs) > 1:
            raise ValueError(f"a link of {len(envs)} envs needs a group name")
        self.session, self.keys = session, keys
        self.channel, self.envs, self.holder = channel, tuple(envs), holder
        self.group = group or envs[0]  # a single env's group is named after it, as its resets are answered
        self.encoded = encoded
        self.encoders = encoders
        self.step_timeout_s = step_timeout_s
        self.max_retries = max_retries
        # The names of every link its learner steps (this one's included), over which encoders are shared evenly
        # (services.presence.balanced_choice); empty: this link's own rendezvous choice.
        self.siblings: tuple[str, ...] = ()
        self.claimed = [False] * len(envs)  # set by a granted claim; only then does release() send anything
        self.ep = [0] * len(envs)
        self.seq = [0] * len(envs)
        self.priors: list[Prior | None] = [None] * len(envs)  # the last latent's next_prior, for the next action
        self.duplicates_dropped = 0
        self.retries = 0
        self._replies: Inbox[BatchMsg | None] = Inbox(poll_seconds(poll_ms))  # None: an unreadable message
        self._actions: list[tuple[SimAction, DiveMode]] = []  # the step in flight, one per env
        self._resetting: tuple[int, ResetRequest] | None = None  # the reset in flight: (env index, its request)
        self._expected: list[tuple[str, int, int]] = []  # (env, ep, seq) of each item of the awaited reply
        # Steps are answered on the group's key, resets on each env's own (the reset request names no group).
        self._subscribers = [self._replies.subscribe(session, self._reply_key(name), self._read)
                             for name in dict.fromkeys((self.group, *self.envs))]  # fmt: skip
        self._publisher = session.declare_publisher(
            keys.action(channel, self.group), congestion_control=zenoh.CongestionControl.BLOCK
        )

    @property
    def name(self) -> str:
        return f"{self.channel}/{self.group}"

    def _reply_key(self, group: str) -> str:
        if self.encoded:
            return self.keys.latent(self.channel, group)
        return self.keys.obs(self.channel, group, DIRECT_ROUTE)

    def _env_name(self, index: int) -> str:
        return f"{self.channel}/{self.envs[index]}"

    def _read(self, sample: zenoh.Sample) -> BatchMsg | None:
        """Where the Inbox hands a message over: decoded, or None (logged) when unreadable."""
        try:
            return BatchMsg.decode(sample.payload.to_bytes())
        except BadMessage as exc:
            log.warning("%s: dropped an unreadable reply: %s", self.name, exc)
            return None

    # --- control, per env ------------------------------------------------------------------------
    def claim(self, timeout_s: float = 5.0, index: int = 0) -> EnvState:
        reply = control.request(self.session, self._ctl(index), ClaimRequest(self.holder), timeout_s)
        self.claimed[index] = True
        return reply

    def release(self, index: int | None = None) -> None:
        """Give back env ``index`` (default: every env) if this link claimed it; a refused claim holds nothing."""
        for each in range(len(self.envs)) if index is None else [index]:
            if not self.claimed[each]:
                continue
            self.claimed[each] = False
            try:
                control.request(self.session, self._ctl(each), ReleaseRequest(self.holder), 2.0)
            except control.ControlError as exc:
                log.warning("%s: release failed: %s", self._env_name(each), exc)

    def _ctl(self, index: int) -> str:
        return self.keys.ctl(self.channel, self.envs[index])

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
        index: int = 0,
    ) -> None:
        """Start episode ``ep`` of env ``index``; ``noise`` switches the sim's image noise (on, off, a map of noise
        settings), ``latency`` its camera and control delays (a map of sim_service.latency settings) and ``scene``
        its scenery (a map of sim_service.scenery settings); None leaves each as it is."""
        self.ep[index], self.seq[index], self.priors[index] = ep, 0, None  # a new episode's target: the image centre
        self._resetting = (index, ResetRequest(self.holder, ep, seed, noise=noise, latency=latency, scene=scene))
        self._expected = [(self.envs[index], ep, 0)]
        try:
            self._send()
        except control.ControlTimeout as exc:  # a busy or restarting sim: wait() re-sends it, like a step
            log.warning("%s: reset unanswered (%s); will retry", self._env_name(index), exc)

    def send(self, actions: Sequence[SimAction], dive_mode: DiveMode = DiveMode.DEPTH_HOLD) -> None:
        """The next step of every env, one action each in the link's order, in one message."""
        if len(actions) != len(self.envs):
            raise ValueError(f"{self.name}: {len(actions)} actions for {len(self.envs)} envs")
        self.seq = [seq + 1 for seq in self.seq]
        self._actions = [(action, dive_mode) for action in actions]
        self._resetting = None
        self._expected = list(zip(self.envs, self.ep, self.seq, strict=True))
        self._send()

    def _send(self) -> None:
        """Send the step or reset in flight, routed anew (the same (ep, seq) each time: a retry is a repeat)."""
        route = self._route()
        if self._resetting is not None:
            index, reset = self._resetting
            control.request(self.session, self._ctl(index), replace(reset, route=route), self.step_timeout_s)
            return
        items = tuple(
            BatchItem.of(env, ActionMsg(ep, seq, action, dive_mode, route, self.holder, prior=prior))
            for (env, ep, seq), (action, dive_mode), prior in zip(
                self._expected, self._actions, self.priors, strict=True
            )
        )
        self._publisher.put(BatchMsg(self.group, self.holder, items).encode())

    def wait(self) -> list[Frame]:
        """The replies to the last send, one per env it named, in order; re-sends the same steps on each timeout
        (up to ``max_retries`` times, counted in ``retries``), then :class:`StepTimeout` naming what is missing.
        A re-send nobody answered is waited out like a lost one; a refused one (:class:`ControlError`, e.g. a
        restarted sim's "not claimed") is raised, and so is a refused step (:class:`StepRefused`)."""
        for attempt in range(self.max_retries + 1):
            deadline = time.monotonic() + self.step_timeout_s
            while (remaining := deadline - time.monotonic()) > 0:
                try:
                    batch = self._replies.get(remaining)
                except queue.Empty:
                    break
                if (replies := self._match(batch)) is not None:
                    return replies
            self.retries += 1
            log.warning("%s: no reply within %.1f s (try %d); re-sending", self.name, self.step_timeout_s, attempt + 1)
            try:
                self._send()
            except control.ControlTimeout as exc:
                log.warning("%s: re-send failed: %s", self.name, exc)
        raise StepTimeout(self._missing_service_message())

    def _match(self, batch: BatchMsg | None) -> list[Frame] | None:
        """The replies if ``batch`` answers what is in flight; raises StepRefused for a refusal of it; else None
        (counted when it answers earlier steps)."""
        if batch is None or batch.to not in (self.holder, ""):
            return None  # unreadable, or the answer to somebody else's actions on these envs
        if [(item.env, item.ep, item.seq) for item in batch.items] != self._expected:
            self.duplicates_dropped += 1  # a late or repeated reply to an earlier step
            return None
        replies = []
        for item in batch.items:
            if item.error:
                raise StepRefused(f"{self.channel}/{item.env}: {item.error}")
            try:
                replies.append(decode_reply(item, self.encoded))
            except BadMessage as exc:
                log.warning("%s: unreadable reply for env %s: %s; waiting for a re-send", self.name, item.env, exc)
                return None
        indices = [self._resetting[0]] if self._resetting is not None else range(len(self.envs))  # envs answered
        for index, (_, prior) in zip(indices, replies, strict=True):
            self.priors[index] = prior
        return [frame for frame, _ in replies]

    def _missing_service_message(self) -> str:
        steps = ", ".join(f"{self.channel}/{env} episode {ep} seq {seq}" for env, ep, seq in self._expected)
        waited = f"{self.max_retries + 1} tries of {self.step_timeout_s:.1f} s"
        if self.encoded and self.encoders is not None:
            live = sorted(self.encoders.members())
            return (
                f"no latent for {steps} after {waited}; live encoders: {live or 'none'}. "
                "Are `swimm sim` and `swimm encoder` running and connected to the same router and namespace?"
            )
        return f"no observation for {steps} after {waited}. Is `swimm sim` running and connected?"

    def close(self) -> None:
        self.release()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._publisher.undeclare()
