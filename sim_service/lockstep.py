"""One served environment: a World plus who holds it and the (episode, seq) it is at.

This is the lock-step contract, free of Zenoh so it can be tested directly:

* an env is driven only by the claimant that holds it;
* ``reset`` starts episode ``ep`` at seq 0; repeating the same reset replays
  the cached observation instead of drawing a new episode;
* action ``seq`` must be the next one (current + 1) and steps the world once;
  the current ``seq`` again is a retry and is answered from the cache
  without stepping; anything else is refused with the reason;
* each observation carries its action's ``prior`` (a retry's too), a reset's none.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

from services.messages import DIRECT_ROUTE, UNCLAIMED, ActionMsg, BatchItem, EnvState, ObservationMsg, Prior
from sim_service.latency import LatencySettings
from sim_service.noise import NoiseSettings
from sim_service.scenery import SceneSettings
from sim_service.world import World

log = logging.getLogger(__name__)


class Refusal(Exception):
    """A request this env will not carry out; ``str(exc)`` is sent back to the sender."""


@dataclass
class Outcome:
    item: BatchItem  # the observation to publish, as its env's item of a step message
    replayed: bool  # True when answered from the cache without stepping


class LockstepEnv:
    def __init__(self, channel: str, env: str, world: World) -> None:
        self.channel = channel
        self.env = env
        self.world = world
        self.holder: str | None = None
        self.ep = 0
        self.seq = 0
        self.seed: int | None = None
        self._last: ObservationMsg | None = None
        self.route = DIRECT_ROUTE  # where this env's observations go (set by reset and each action)
        self.action = (0.0, 0.0, 0.0, 0.0)  # held between steps in real-time mode
        self.prior: Prior | None = None  # held with the action in real-time mode
        self.pending: ActionMsg | None = None  # real-time mode: the latest action, applied at the next tick

    @property
    def name(self) -> str:
        return f"{self.channel}/{self.env}"

    def claim(self, holder: str) -> None:
        if self.holder not in (None, holder):
            raise Refusal(f"env {self.name} is held by {self.holder}")
        if self.holder != holder:
            log.info("env %s claimed by %s", self.name, holder)
        self.holder = holder

    def release(self, holder: str) -> None:
        if self.holder != holder:
            raise Refusal(f"env {self.name} is not held by {holder} (holder: {self.holder})")
        self.holder = None
        log.info("env %s released by %s", self.name, holder)

    def lapse(self, gone: set[str]) -> None:
        """Free the env when its holder's liveliness token went away."""
        if self.holder in gone:
            log.warning("env %s: holder %s is gone; claim lapsed", self.name, self.holder)
            self.holder = None

    def _check_holder(self, sender: str) -> None:
        if self.holder is None:
            raise Refusal(f"env {self.name} {UNCLAIMED}; claim it before driving it")
        if sender != self.holder:
            raise Refusal(f"env {self.name} is held by {self.holder}, not {sender or 'an anonymous sender'}")

    def reset(
        self,
        sender: str,
        ep: int,
        seed: int,
        route: str = DIRECT_ROUTE,
        noise: bool | NoiseSettings | None = None,
        latency: LatencySettings | None = None,
        scene: SceneSettings | None = None,
    ) -> Outcome:
        self._check_holder(sender)
        self.route = route
        if ep == self.ep and self.seq == 0 and self._last is not None and seed == self.seed:
            return self._replay(None)
        if ep <= self.ep and self._last is not None:
            raise Refusal(f"env {self.name}: episode {ep} is not after the current episode {self.ep}")
        if latency is not None:
            self.world.configure_latency(latency)
        telemetry, image = self.world.reset(seed, noise, scene)
        self.ep, self.seq, self.seed = ep, 0, seed
        self.action, self.prior = (0.0, 0.0, 0.0, 0.0), None
        return self._emit(telemetry, image)

    def act(self, msg: ActionMsg) -> Outcome:
        self._check_holder(msg.sender)
        self.route = msg.route
        if msg.ep != self.ep or self._last is None:
            raise Refusal(f"env {self.name}: action for episode {msg.ep}, but the current episode is {self.ep}")
        if msg.seq == self.seq:
            return self._replay(msg.prior)
        if msg.seq != self.seq + 1:
            raise Refusal(f"env {self.name}: action seq {msg.seq} out of order (expected {self.seq + 1})")
        telemetry, image = self.world.step(msg.action, msg.dive_mode)
        self.seq, self.prior = msg.seq, msg.prior
        return self._emit(telemetry, image)

    def step_realtime(self) -> Outcome | None:
        """Real-time mode: advance once with the latest action (held when none came)."""
        if self._last is None:
            return None
        if self.pending is not None:
            self._check_holder(self.pending.sender)
            self.action, self.prior, self.route = self.pending.action, self.pending.prior, self.pending.route
            self.pending = None
        telemetry, image = self.world.step(self.action)
        self.seq += 1
        return self._emit(telemetry, image)

    def _emit(self, telemetry, image) -> Outcome:
        self._last = ObservationMsg(self.env, self.ep, self.seq, telemetry, image, time.time(), self.prior)
        return Outcome(BatchItem.of(self.env, self._last), replayed=False)

    def _replay(self, prior: Prior | None) -> Outcome:
        """The cached observation again, with the retry's prior: a failover's retry goes to an encoder that has none."""
        return Outcome(BatchItem.of(self.env, replace(self._last, prior=prior)), replayed=True)

    def state(self) -> EnvState:
        return EnvState(self.channel, self.env, self.holder, self.ep, self.seq)
