"""`swimm sim`: serves LockstepEnvs on the train and eval channels over Zenoh.

Requests reach one worker thread through an Inbox (services/polling.py), without
decoding; the worker owns every World (MuJoCo and its GL context stay on one
thread) and answers each env's requests in the order they came, so a run is
reproducible whatever the network does. Between an observation and the next
action, when nothing else waits, the worker prepares that env's next step
(``World.prepare_step``), which takes the dolphin's swim off the round trip.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from dataclasses import asdict, dataclass, field

import zenoh

from services import control
from services.control import CLAIMANT_ROLES
from services.keys import Keys
from services.lifecycle import Service, serve_until_signalled
from services.low_latency import largest_low_latency_image_size, low_latency_group_problem, observation_bytes
from services.messages import (
    DIRECT_ROUTE,
    ActionMsg,
    AnyControlRequest,
    BadMessage,
    BatchItem,
    BatchMsg,
    ClaimRequest,
    EnvState,
    InfoReply,
    InfoRequest,
    Refused,
    ReleaseRequest,
    ResetReply,
    ResetRequest,
    decode_request,
)
from services.metrics import Metrics, MetricsPublisher
from services.polling import Inbox, poll_seconds
from services.presence import Roster, announce, live_now
from services.session import LOW_LATENCY_MAX_MESSAGE_BYTES, open_session
from services.settings import check_ranges
from sim_service.latency import describe_latency, latency_option
from sim_service.lockstep import LockstepEnv, Outcome, Refusal
from sim_service.noise import describe_noise, noise_option
from sim_service.scenery import scene_option
from sim_service.settings import SimSettings
from sim_service.world import World

log = logging.getLogger(__name__)


# The worker's requests. ``received_at``: when one reached the inbox (polling: the worker).
@dataclass
class _Step:
    """A group's actions, still encoded; its key names the channel and group."""

    payload: bytes
    key: str
    received_at: float = field(default_factory=time.perf_counter)


@dataclass
class _Control:
    """A control request to ``env``, to decode and answer."""

    env: LockstepEnv
    query: zenoh.Query
    received_at: float = field(default_factory=time.perf_counter)


@dataclass
class _Lapse:
    """Holders whose tokens stayed gone past the grace: their claims lapse."""

    gone: set[str]


_Request = _Step | _Control | _Lapse


def check_fits_low_latency(settings: SimSettings) -> None:
    """Refuse, before any world is built, observations too large for a low-latency session to send."""
    world = settings.world
    if not settings.zenoh.low_latency or not world.render:
        return
    if world.image_size > largest_low_latency_image_size():
        raise ValueError(
            f"--low-latency sends messages of at most {LOW_LATENCY_MAX_MESSAGE_BYTES} bytes, and "
            f"{world.image_size} px observations take up to {observation_bytes(world.image_size)}: "
            f"use --image-size {largest_low_latency_image_size()} or less, or leave --low-latency off"
        )


def check(settings: SimSettings) -> None:
    """Refuse, before any world is built, settings no sim can serve (`swimm up` runs it before it starts one)."""
    check_ranges(settings)
    if settings.train_envs == 0 and settings.eval_envs == 0:
        raise ValueError("--train-envs 0 and --eval-envs 0: the sim would serve no env; give either at least 1")
    settings.world.check()
    check_fits_low_latency(settings)


class SimResponder(Service):
    def __init__(self, settings: SimSettings) -> None:
        check(settings)
        self.settings = settings
        self.keys = Keys(settings.zenoh.namespace)
        self.ident = settings.ident or f"sim-{os.getpid()}"
        self.metrics = Metrics()
        self._inbox: Inbox[_Request | None] = Inbox(poll_seconds(settings.poll_ms))
        self._stop = threading.Event()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._envs: list[LockstepEnv] = []
        self._unprepared: set[LockstepEnv] = set()  # answered since they last prepared their next step
        self._ready = threading.Event()
        self._build_error: Exception | None = None
        self._worker = threading.Thread(target=self._work, name="sim-worker", daemon=True)

    # --- set-up -------------------------------------------------------------------------------
    def start(self) -> None:
        self._worker.start()  # creates the Worlds (and their GL contexts) on its own thread
        if not self._ready.wait(timeout=120):
            raise RuntimeError("the sim worker did not build its worlds within 120 s")
        if self._build_error is not None:
            raise RuntimeError(f"the sim could not build its worlds: {self._build_error}") from self._build_error
        own = self.resources.enter_context
        self.session = own(open_session(self.settings.zenoh, role="sim"))
        for role in CLAIMANT_ROLES:
            own(Roster(self.session, self.keys, role, self._on_roster_change))
        for env in self._envs:
            own(
                self.session.declare_queryable(
                    self.keys.ctl(env.channel, env.env),
                    lambda query, env=env: self._inbox.put(_Control(env, query)),
                )
            )
        for channel in {env.channel for env in self._envs}:
            own(
                self._inbox.subscribe(
                    self.session,
                    self.keys.actions(channel),
                    lambda sample: _Step(sample.payload.to_bytes(), str(sample.key_expr)),
                )
            )
        own(announce(self.session, self.keys, "sim", self.ident))
        own(MetricsPublisher(self.session, self.keys, "sim", self.ident, self.metrics))
        log.info(
            "sim %s serving %d train and %d eval envs under %s (%s); image noise: %s; latency: %s; scenery: %s",
            self.ident,
            self.settings.train_envs,
            self.settings.eval_envs,
            self.keys.namespace,
            "real-time" if self.settings.realtime else "lock-step",
            describe_noise(self.settings.world.noise),
            describe_latency(self.settings.world.latency),
            self.settings.world.scene.preset,
        )

    def _on_roster_change(self, joined: set[str], left: set[str]) -> None:
        """A holder's token went: free its envs unless it is back within the grace period.

        Tokens also vanish while a router restarts; the grace keeps claims across such an outage.
        """
        if left:
            timer = threading.Timer(self.settings.claim_grace_s, self._lapse_if_still_gone, args=(left,))
            timer.daemon = True
            timer.start()

    def _lapse_if_still_gone(self, left: set[str]) -> None:
        """On the grace timer's thread: ask the network which of ``left`` are back, and lapse the others' claims."""
        if self._stop.is_set():
            return
        back = set().union(*(live_now(self.session, self.keys, role) for role in CLAIMANT_ROLES))
        if left - back:
            self._inbox.put(_Lapse(left - back))

    # --- the worker -----------------------------------------------------------------------------
    def _build_envs(self) -> None:
        """Every served env's World, on the worker thread; they share the first one's renderer (one GL context per
        sim process: the worlds are stepped one after another, and each context costs CPU every frame)."""
        first = {"train": self.settings.first_train_env, "eval": 0}
        renderer_of: World | None = None
        for channel, count in (("train", self.settings.train_envs), ("eval", self.settings.eval_envs)):
            for index in range(first[channel], first[channel] + count):
                world = World(self.settings.world, share_renderer_with=renderer_of)
                renderer_of = renderer_of or world
                self._envs.append(LockstepEnv(channel, str(index), world))
        self._by_name = {(env.channel, env.env): env for env in self._envs}

    def _work(self) -> None:
        try:
            self._build_envs()
        except Exception as exc:  # start() raises it: the worker has nothing to serve
            self._build_error = exc
            return
        finally:
            self._ready.set()
        period = self.settings.world.physics_dt
        next_tick = time.perf_counter()
        while True:
            timeout = max(0.0, next_tick - time.perf_counter()) if self.settings.realtime else 0.5
            try:
                request = self._next_request(timeout)
            except queue.Empty:
                request = None
                if self._stop.is_set():
                    break
            if request is None and self._stop.is_set():
                break  # stop()'s sentinel, behind every request that came before it
            if request is not None:
                self._handle(request)
            if self.settings.realtime and time.perf_counter() >= next_tick:
                next_tick += period
                self._tick_realtime()
        for env in self._envs:
            env.world.close()

    def _next_request(self, timeout: float) -> _Request | None:
        """The next request, waited for up to ``timeout``.

        While the inbox is empty, each env answered since it last prepared prepares its next step
        (``World.prepare_step``), one env at a time with a look at the inbox between them, so the work leaves
        the round trip: it runs while the observation travels and the learner decides. A request that comes
        first is served at once, its step preparing itself.
        """
        while self._unprepared:
            try:
                return self._inbox.get(timeout=0.0)
            except queue.Empty:
                self._prepare(self._unprepared.pop())
        return self._inbox.get(timeout)

    def _prepare(self, env: LockstepEnv) -> None:
        try:
            env.world.prepare_step()
            self.metrics.count("steps_prepared")
        except Exception:  # the step will run into it again and report it; the worker must live on
            self.metrics.count("errors_internal")
            log.exception("internal error while preparing the next step of %s", env.name)

    def _handle(self, request: _Request) -> None:
        try:
            match request:
                case _Step():
                    self._handle_step(request)
                case _Control():
                    self._handle_control(request)
                case _Lapse(gone=gone):
                    for env in self._envs:
                        env.lapse(gone)
        except Exception:  # a bug in one request must not take the sim down
            self.metrics.count("errors_internal")
            log.exception("internal error while handling a %s", type(request).__name__)

    def _handle_step(self, request: _Step) -> None:
        """A group's actions (one env's: a group of one): each env steps in order, and one message answers them all,
        each item its env's observation or refusal. A group is one sim's: one that holds none of this sim's envs is
        left to the others, and an env of it this sim does not serve is refused."""
        try:
            batch = BatchMsg.decode(request.payload)
            channel, group = self.keys.parse_step_key(request.key)
        except (BadMessage, ValueError) as exc:  # no env to answer: the learner's timeout names the step
            self.metrics.count("errors_refused")
            log.warning("refused a group of actions on %s: %s", request.key, exc)
            return
        if not any((channel, item.env) in self._by_name for item in batch.items):
            return  # another sim's group: sims serving one run side by side all hear every group
        items, route = [], DIRECT_ROUTE
        too_large = self._group_problem(len(batch.items))
        for item in batch.items:
            env = self._by_name.get((channel, item.env))
            try:
                msg = ActionMsg.from_item(item)
                route = msg.route
                if env is None:
                    raise Refusal(f"env {channel}/{item.env} is not served by sim {self.ident}")
                if too_large:
                    raise Refusal(too_large)  # refused before stepping, so a smaller group can take the step
                if self.settings.realtime:
                    if len(batch.items) > 1:
                        raise Refusal("a real-time sim takes actions one env at a time, not in groups")
                    env.pending = msg  # applied at the next tick, which answers it
                    return
                outcome = env.act(msg)
            except (BadMessage, Refusal) as exc:
                self.metrics.count("errors_refused")
                log.warning("refused the action of %s/%s in group %s: %s", channel, item.env, group, exc)
                items.append(BatchItem(item.env, item.ep, item.seq, error=str(exc)))
                continue
            items.append(outcome.item)
            self.metrics.count("replays" if outcome.replayed else "steps")
            self._unprepared.add(env)
        self._answer(channel, group, route, batch.sender, items)
        self.metrics.observe_ms("step", (time.perf_counter() - request.received_at) * 1e3 / len(batch.items))

    def _group_problem(self, group_size: int) -> str | None:
        """Why this sim cannot answer a group of ``group_size`` envs in one message, or None."""
        world = self.settings.world
        if not self.settings.zenoh.low_latency or not world.render:
            return None
        return low_latency_group_problem(group_size, world.image_size)

    def _tick_realtime(self) -> None:
        for env in self._envs:
            try:
                outcome = env.step_realtime()
            except Refusal as exc:
                self.metrics.count("errors_refused")
                log.warning("refused action on %s: %s", env.name, exc)
                self._answer(env.channel, env.env, env.route, "", [BatchItem(env.env, env.ep, env.seq, error=str(exc))])
                continue
            if outcome is not None:
                self._publish(env, env.route, env.holder or "", outcome, time.perf_counter())

    def _handle_control(self, request: _Control) -> None:
        """Answer a control request with its reply, or with a Refused naming what was wrong."""
        env, query = request.env, request.query
        answer: EnvState | Refused
        try:
            message = decode_request(query.payload.to_bytes() if query.payload is not None else b"")
            answer = self._carry_out(env, message, request.received_at)
            self.metrics.count(f"ctl_{message.OP}")
        except (BadMessage, Refusal) as exc:
            self.metrics.count("errors_refused")
            log.warning("refused control request on %s: %s", env.name, exc)
            answer = Refused(str(exc))
        control.reply(query, answer)

    def _carry_out(self, env: LockstepEnv, message: AnyControlRequest, received_at: float) -> EnvState:
        match message:
            case InfoRequest():
                return InfoReply(**asdict(env.state()), sim=self.ident, image_size=self.settings.world.image_size)
            case ClaimRequest(holder=holder):
                env.claim(holder)
                return env.state()
            case ReleaseRequest(holder=holder):
                env.release(holder)
                return env.state()
            case ResetRequest():
                return self._reset(env, message, received_at)

    def _reset(self, env: LockstepEnv, message: ResetRequest, received_at: float) -> ResetReply:
        """Start the episode and publish its observation as the env's group of one."""
        try:
            noise, latency = noise_option(message.noise), latency_option(message.latency)
            scene = scene_option(message.scene)
        except ValueError as exc:  # the maps' settings, which only the sim knows
            raise BadMessage(f"reset's {exc}") from None
        outcome = env.reset(message.holder, message.ep, message.seed, message.route, noise, latency, scene)
        self._publish(env, message.route, message.holder, outcome, received_at)
        return ResetReply(**asdict(env.state()), replayed=outcome.replayed)

    def _publisher(self, key: str) -> zenoh.Publisher:
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            self._publishers[key] = self.resources.enter_context(publisher)
        return publisher

    def _answer(self, channel: str, group: str, route: str, to: str, items: list[BatchItem]) -> None:
        """One message of observations (or refusals) for ``group``, to the encoder ``route`` or the learner ``to``."""
        reply = BatchMsg(group, self.ident, tuple(items), to)
        self._publisher(self.keys.obs(channel, group, route)).put(reply.encode())

    def _publish(self, env: LockstepEnv, route: str, to: str, outcome: Outcome, received_at: float) -> None:
        """One env's observation outside a step (a reset's, a real-time tick's): as its own group of one."""
        reply = BatchMsg.alone(outcome.item, self.ident, to)
        self._publisher(self.keys.obs(env.channel, env.env, route)).put(reply.encode())
        self.metrics.count("replays" if outcome.replayed else "steps")
        self.metrics.observe_ms("step", (time.perf_counter() - received_at) * 1e3)
        if not self.settings.realtime:
            self._unprepared.add(env)

    # --- shutdown -------------------------------------------------------------------------------
    def close(self) -> None:
        """Drain queued requests, then undeclare everything and close the session; safe to call twice."""
        self._stop.set()
        self._inbox.put(None)
        if self._worker.is_alive():
            self._worker.join(timeout=30)
        super().close()
        log.info("sim %s stopped: %s", self.ident, self.metrics.snapshot())


def run(settings: SimSettings) -> None:
    serve_until_signalled(SimResponder(settings))
