"""Taking the next message from a queue by polling it before sleeping on it.

A lock-step process spends most of its time waiting for the other side's message. Blocked on its inbox it
sleeps, and the message then wakes it on a cold CPU: on the 2-core development box a World step costs 0.51 ms
after a 2 ms sleep against 0.36 ms back to back, and each hop adds the wake-up of a sleeping thread. Polling for
a few milliseconds before blocking keeps the process awake for the reply it is about to get; the sim's one-env
round trip gets about 25% faster when both sides poll (docs/benchmarks.md).

The price is a busy core while waiting, so polling is a setting, off by default: it pays where each process
has a core of its own (one env served to one learner), not where the sim, the encoders and a training learner
share two cores, since a poller then takes CPU from the very process it waits for.
"""

from __future__ import annotations

import os
import queue
import sys
import time
from typing import TypeVar

T = TypeVar("T")

#: The GIL switch interval of a process that polls. The Zenoh thread that delivers a message into the queue
#: needs the GIL, which the poller keeps taking back; at Python's default interval (5 ms) it can wait that long.
#: Measured with `swimm bench sim`: 20 us gave the fastest round trips, 100 us and 5 us slower ones.
POLLING_SWITCH_INTERVAL_S = 2e-5


def prepare_to_poll(poll_ms: float) -> float:
    """Check ``poll_ms``, shorten the switch interval when it is positive; returns the poll time in seconds."""
    if poll_ms < 0:
        raise ValueError(f"poll_ms must be >= 0 (0: block at once), got {poll_ms}")
    if poll_ms > 0:
        sys.setswitchinterval(min(sys.getswitchinterval(), POLLING_SWITCH_INTERVAL_S))
    return poll_ms / 1e3


def get_polled(inbox: queue.Queue[T], poll_s: float, timeout: float) -> T:
    """The next item: polled for up to ``poll_s``, yielding the CPU between tries, then waited for until
    ``timeout`` (counted from the call) runs out; raises queue.Empty then, as ``Queue.get`` does."""
    if poll_s <= 0:  # the default: block at once, as Queue.get
        return inbox.get(timeout=timeout)
    start = time.perf_counter()
    while time.perf_counter() - start < poll_s:
        try:
            return inbox.get_nowait()
        except queue.Empty:
            os.sched_yield()  # releases the GIL, so the delivering thread can put the item
    return inbox.get(timeout=max(0.0, timeout - (time.perf_counter() - start)))
