"""Simulator benchmark: in-process step+render rate vs the distributed lock-step round trip.

Everything runs in one invocation on the same machine, so the ratios are a fair comparison. The distributed
runs start `swimm router` and `swimm sim` as separate processes and step one env from this one, three ways:

- peer, polling (the headline keys): the sim and this process join as Zenoh peers (the router introduces
  them, each message goes directly from one to the other) and each side polls for the next message for
  :data:`POLL_MS` before sleeping on it (`swimm sim --poll-ms`, ``ProxySettings.poll_ms``): how to serve one
  env when each process has a core to itself;
- peer, blocking (the ``blocking_*`` keys): the same, each side sleeping on its inbox at once, as `swimm up`
  runs (there the processes share the cores with a training learner and the encoders);
- client (the ``routed_*`` keys; what deploy/docker-compose.yml runs): every message goes through the router,
  both sides blocking.

Each adds the msgpack codec, the Zenoh hops and the process switches to the in-process step, nothing else.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from services.keys import Keys
from services.presence import Roster, announce
from services.procs import ProcessGroup
from services.session import open_session
from services.settings import ZenohSettings
from sim_service.world import World


def random_actions(steps: int, seed: int = 0) -> list[tuple[float, float, float, float]]:
    rng = np.random.default_rng(seed)
    return [tuple(float(x) for x in row) for row in rng.uniform(-1, 1, (steps, 4))]


def inprocess_rate(steps: int) -> float:
    world = World()
    try:
        world.reset(1)
        actions = random_actions(steps)
        start = time.perf_counter()
        for action in actions:
            world.step(action)
        return steps / (time.perf_counter() - start)
    finally:
        world.close()


POLL_MS = 2.0  # the polling run's wait before sleeping, each side: longer than a round trip (about 1 ms)


def distributed_rate(steps: int, log_dir: Path, mode: str, poll_ms: float) -> tuple[float, np.ndarray]:
    """Steps/s and per-step round-trip times (s) of one env served by `swimm sim`, both sides joined in ``mode``
    and polling for ``poll_ms`` before sleeping on their inboxes."""
    from learner_service.link import RemoteEnvLink, new_holder_id

    with ProcessGroup(log_dir) as group:
        endpoint = group.start_router()
        settings = ZenohSettings(mode=mode, connect=[endpoint], namespace="swimm/bench")
        sim_args = ("--mode", mode, "--connect", endpoint, "--namespace", settings.namespace, "--eval-envs", "0")
        group.start("sim", "sim", *sim_args, "--poll-ms", str(poll_ms))
        session = open_session(settings, role="bench")
        keys = Keys(settings.namespace)
        holder = new_holder_id("learner")
        token = announce(session, keys, "learner", holder)
        sims = Roster(session, keys, "sim")
        try:
            sims.wait_for(1, timeout_s=60)
            link = RemoteEnvLink(session, keys, "train", "0", holder, encoded=False, poll_ms=poll_ms)
            link.claim()
            link.send_reset(1, 1)
            link.wait()
            actions = random_actions(steps)
            round_trips = np.empty(steps)
            start = time.perf_counter()
            for i, action in enumerate(actions):
                sent = time.perf_counter()
                link.send_action(action)
                link.wait()
                round_trips[i] = time.perf_counter() - sent
            rate = steps / (time.perf_counter() - start)
            link.close()
        finally:
            sims.close()
            token.undeclare()
            session.close()
    return rate, round_trips


#: The distributed runs: key prefix, Zenoh mode, poll time (ms). Polling goes last: it leaves this process's
#: GIL switch interval short (services/polling.py), which the blocking runs should not inherit.
DISTRIBUTED_RUNS = (("blocking_", "peer", 0.0), ("routed_", "client", 0.0), ("", "peer", POLL_MS))


def run(steps: int = 2000) -> dict:
    inprocess = inprocess_rate(steps)
    measured: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="swimm-bench-") as tmp:
        for prefix, mode, poll_ms in DISTRIBUTED_RUNS:
            rate, round_trips = distributed_rate(steps, Path(tmp) / (prefix or "polling"), mode, poll_ms)
            measured[prefix] = {
                f"{prefix or 'distributed_'}steps_per_s": round(rate, 1),
                f"{prefix}ratio": round(rate / inprocess, 3),
                f"{prefix}p50_ms": percentile_ms(round_trips, 50),
                f"{prefix}p99_ms": percentile_ms(round_trips, 99),
            }
    headline_first = sorted(measured, key=bool)
    result = {"inprocess_steps_per_s": round(inprocess, 1)}
    for prefix in headline_first:
        result |= measured[prefix]
    return result | {"topology": "peer", "poll_ms": POLL_MS, "steps": steps}


def percentile_ms(seconds: np.ndarray, q: float) -> float:
    return round(float(np.percentile(seconds, q)) * 1e3, 3)
