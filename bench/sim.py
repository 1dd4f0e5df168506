"""Simulator benchmark: in-process step+render rate vs the distributed lock-step round trip.

Both halves run in one invocation on the same machine, so the ratio is a
fair comparison: the distributed half adds the msgpack codec, two Zenoh
hops through a Python router and the process switch, nothing else.
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


def distributed_rate(steps: int, log_dir: Path) -> tuple[float, np.ndarray]:
    """Steps/s and per-step round-trip times (s) of one env served by `swimm sim` through `swimm router`."""
    from learner_service.link import RemoteEnvLink, new_holder_id

    with ProcessGroup(log_dir) as group:
        endpoint = group.start_router()
        settings = ZenohSettings(connect=[endpoint], namespace="swimm/bench")
        group.start("sim", "sim", "--connect", endpoint, "--namespace", settings.namespace, "--eval-envs", "0")
        session = open_session(settings, role="bench")
        keys = Keys(settings.namespace)
        holder = new_holder_id("learner")
        token = announce(session, keys, "learner", holder)
        sims = Roster(session, keys, "sim")
        try:
            sims.wait_for(1, timeout_s=60)
            link = RemoteEnvLink(session, keys, "train", "0", holder, encoded=False)
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


def run(steps: int = 2000) -> dict:
    inprocess = inprocess_rate(steps)
    with tempfile.TemporaryDirectory(prefix="swimm-bench-") as tmp:
        distributed, round_trips = distributed_rate(steps, Path(tmp))
    return {
        "inprocess_steps_per_s": round(inprocess, 1),
        "distributed_steps_per_s": round(distributed, 1),
        "ratio": round(distributed / inprocess, 3),
        "p50_ms": round(float(np.percentile(round_trips, 50)) * 1e3, 3),
        "p99_ms": round(float(np.percentile(round_trips, 99)) * 1e3, 3),
        "steps": steps,
    }
