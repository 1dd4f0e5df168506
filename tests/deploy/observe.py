"""What the deployment tests watch from outside a stack, through the router's published port: every latent."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

import pytest

from services.keys import Keys
from services.messages import LatentMsg
from sim_service.settings import WorldSettings


class LatentLog:
    """Every latent on ``<ns>/train/*/latent``, as seen by an outside observer."""

    def __init__(self, session, keys: Keys) -> None:
        self.rows: list[tuple[str, int, int, float, str]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(f"{keys.namespace}/train/*/latent", self._on_latent)

    def _on_latent(self, sample) -> None:
        msg = LatentMsg.decode(sample.payload.to_bytes())
        with self._lock:
            self.rows.append((msg.env, msg.ep, msg.seq, msg.telemetry.sim_time, msg.encoder))

    def snapshot(self) -> list[tuple[str, int, int, float, str]]:
        with self._lock:
            return list(self.rows)

    def steps(self) -> int:
        return len({row[:3] for row in self.snapshot()})

    def close(self) -> None:
        self._sub.undeclare()


def wait_until(condition, timeout_s: float, what: str, stack) -> None:
    """Poll ``condition`` each second; past ``timeout_s`` fail naming ``what``, with the ``stack.logs()``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}\n{stack.logs()}")
        time.sleep(1.0)


def check_no_step_lost_or_repeated(rows: list[tuple[str, int, int, float, str]], envs: int) -> None:
    """Each (env, ep) seen: seqs 0..n without a gap, and the sim's clock at seq * dt (applied once each).

    A latent may arrive twice (a re-sent step is answered from the sim's cache and encoded again); both
    copies then carry the same clock. Episodes already running when the observer joined are skipped.
    """
    dt = WorldSettings().physics_dt
    clocks: dict[tuple[str, int], dict[int, set[int]]] = defaultdict(lambda: defaultdict(set))
    for env, ep, seq, sim_time, _ in rows:
        clocks[(env, ep)][seq].add(round(sim_time / dt))
    whole = [key for key, seqs in clocks.items() if 0 in seqs]
    assert len(whole) >= envs
    for key in whole:
        seqs = clocks[key]
        assert sorted(seqs) == list(range(max(seqs) + 1)), f"{key}: a step is missing"
        assert all(ticks == {seq} for seq, ticks in seqs.items()), f"{key}: a step was applied twice"
