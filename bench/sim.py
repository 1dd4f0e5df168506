"""Simulator benchmark: in-process step+render rate vs the distributed lock-step round trip.

Everything runs in one invocation on the same machine. `swimm router` and three `swimm sim` processes (one per
way of serving, each in its own namespace) start first; then the steps are taken in rounds, and each round
runs a block of in-process steps and a block through each sim, back to back. A virtual machine's speed
drifts by a third within a minute; measured in rounds, every rate sees the same drift, so the ratios compare
like with like. The four ways:

- peer, polling (the headline keys): the sim and this process join as Zenoh peers (the router introduces
  them, each message goes directly from one to the other) over Zenoh's low-latency transport
  (``--low-latency``), and each side polls for the next message for :data:`POLL_MS` before napping between
  looks (`swimm sim --poll-ms`, ``ProxySettings.poll_ms``): how to serve one env when each process has a core
  to itself;
- peer, polling, standard transport (the ``standard_*`` keys): the same over Zenoh's default transport, which
  shows what the low-latency one adds;
- peer, blocking (the ``blocking_*`` keys): the standard transport, each side sleeping on its inbox at once,
  as `swimm up` runs (there the processes share the cores with a training learner and the encoders);
- client (the ``routed_*`` keys; what deploy/docker-compose.yml runs): every message goes through the router,
  both sides blocking.

Each adds the msgpack codec, the Zenoh hops and the process switches to the in-process step, nothing else.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.keys import Keys
from services.polling import POLLING_SWITCH_INTERVAL_S
from services.presence import Roster, announce
from services.procs import ProcessGroup
from services.session import open_session
from services.settings import ZenohSettings
from sim_service.world import World

POLL_MS = 2.0  # the polling run's wait before sleeping, each side: longer than a round trip (about 1 ms)
ROUNDS = 8  # blocks per way of serving; each round measures every way once
#: Untimed steps each way (and the in-process world) takes first. A fresh process's first few hundred frames
#: are the slowest (Mesa compiles its shaders, caches fill): 1864 steps/s over the first 2000 in-process
#: steps, 2427-2657 over the next ones.
WARMUP_STEPS = 200
DEFAULT_SWITCH_INTERVAL_S = sys.getswitchinterval()  # what a blocking link runs with


@dataclass(frozen=True)
class Way:
    """One way of serving the env: its name, key prefix in the result, Zenoh mode, poll time (ms) and transport."""

    name: str
    prefix: str
    mode: str
    poll_ms: float
    low_latency: bool = False


#: The headline way first, as in the result.
WAYS = (
    Way("polling", "", "peer", POLL_MS, low_latency=True),
    Way("standard", "standard_", "peer", POLL_MS),
    Way("blocking", "blocking_", "peer", 0.0),
    Way("routed", "routed_", "client", 0.0),
)


def random_actions(steps: int, seed: int = 0) -> list[tuple[float, float, float, float]]:
    rng = np.random.default_rng(seed)
    return [tuple(float(x) for x in row) for row in rng.uniform(-1, 1, (steps, 4))]


def _step_inprocess(world: World, actions: list) -> float:
    """Seconds for one World in this process to take ``actions`` back to back."""
    start = time.perf_counter()
    for action in actions:
        world.step(action)
    return time.perf_counter() - start


@dataclass
class Tally:
    """Steps and seconds summed over the blocks of one way, with every round trip."""

    steps: int = 0
    seconds: float = 0.0
    round_trips: list[float] = field(default_factory=list)

    @property
    def rate(self) -> float:
        return self.steps / self.seconds


class ServedEnv:
    """One env of a `swimm sim` process, claimed and reset, stepped lock-step from this process."""

    def __init__(self, group: ProcessGroup, endpoint: str, way: Way, stack: ExitStack) -> None:
        from learner_service.link import RemoteEnvLink, new_holder_id

        self.way = way
        settings = ZenohSettings(
            mode=way.mode, connect=[endpoint], namespace=f"swimm/bench-{way.name}", low_latency=way.low_latency
        )
        sim_args = ("--mode", way.mode, "--connect", endpoint, "--namespace", settings.namespace, "--eval-envs", "0")
        sim_args += ("--low-latency",) if way.low_latency else ()
        group.start(f"sim-{way.name}", "sim", *sim_args, "--poll-ms", str(way.poll_ms))
        session = open_session(settings, role="bench")
        stack.callback(session.close)
        keys = Keys(settings.namespace)
        holder = new_holder_id("learner")
        stack.callback(announce(session, keys, "learner", holder).undeclare)
        sims = Roster(session, keys, "sim")
        stack.callback(sims.close)
        sims.wait_for(1, timeout_s=60)
        self.link = RemoteEnvLink(session, keys, "train", "0", holder, encoded=False, poll_ms=way.poll_ms)
        stack.callback(self.link.close)
        self.link.claim()
        self.link.send_reset(1, 1)
        self.link.wait()

    def step(self, actions: list, tally: Tally) -> None:
        with switch_interval(POLLING_SWITCH_INTERVAL_S if self.way.poll_ms > 0 else DEFAULT_SWITCH_INTERVAL_S):
            start = time.perf_counter()
            for action in actions:
                sent = time.perf_counter()
                self.link.send_action(action)
                self.link.wait()
                tally.round_trips.append(time.perf_counter() - sent)
            tally.seconds += time.perf_counter() - start
        tally.steps += len(actions)


@contextmanager
def switch_interval(seconds: float) -> Iterator[None]:
    """Run a block with the GIL switch interval its way of serving uses (a polling link shortens it)."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def run(steps: int = 2000, rounds: int = ROUNDS) -> dict:
    """``steps`` per way in all, taken in ``rounds`` blocks; the in-process rate over its blocks alike."""
    actions = random_actions(steps)
    blocks = np.array_split(np.arange(steps), rounds)
    inprocess = Tally()
    served = {way.prefix: Tally() for way in WAYS}
    with (
        tempfile.TemporaryDirectory(prefix="swimm-bench-") as tmp,
        ProcessGroup(Path(tmp)) as group,
        ExitStack() as stack,
    ):
        endpoint = group.start_router()
        envs = [ServedEnv(group, endpoint, way, stack) for way in WAYS]
        world = World()
        stack.callback(world.close)
        world.reset(1)
        warmup = random_actions(WARMUP_STEPS, seed=1)
        _step_inprocess(world, warmup)
        for env in envs:
            env.step(warmup, Tally())
        for round_index, block in enumerate(blocks):
            block_actions = [actions[i] for i in block]
            inprocess.seconds += _step_inprocess(world, block_actions)
            inprocess.steps += len(block_actions)
            first = round_index % len(envs)  # each way goes first in some round
            for env in envs[first:] + envs[:first]:
                env.step(block_actions, served[env.way.prefix])
    result = {"inprocess_steps_per_s": round(inprocess.rate, 1)}
    for way in WAYS:
        tally = served[way.prefix]
        round_trips = np.array(tally.round_trips)
        result |= {
            f"{way.prefix or 'distributed_'}steps_per_s": round(tally.rate, 1),
            f"{way.prefix}ratio": round(tally.rate / inprocess.rate, 3),
            f"{way.prefix}p50_ms": percentile_ms(round_trips, 50),
            f"{way.prefix}p99_ms": percentile_ms(round_trips, 99),
        }
    return result | {
        "topology": "peer",
        "transport": "low-latency" if WAYS[0].low_latency else "standard",
        "poll_ms": POLL_MS,
        "steps": steps,
        "rounds": rounds,
    }


def percentile_ms(seconds: np.ndarray, q: float) -> float:
    return round(float(np.percentile(seconds, q)) * 1e3, 3)
