"""A lock-step worker's inbox, which can poll for the next message before sleeping on it.

A lock-step process spends most of its time waiting for the other side's message. Blocked on its inbox it
sleeps, and the message then wakes it on a cold CPU, after the wake-up of a sleeping thread. Polling for a few
milliseconds before blocking keeps the process awake for the reply it is about to get.

The price is a busy core while waiting (and, idle, a look for work every millisecond), so polling is a setting,
off by default: it pays where each process has a core of its own (one env served to one learner), not where the
sim, the encoders and a training learner share two cores, since a poller then takes CPU from the very process
it waits for. docs/benchmarks.md (polling) has the gains and the costs measured.

A message handed over by a Python callback needs the GIL on the Zenoh thread that received it, and a poller
keeps taking the GIL back. :class:`Inbox` lets a polling worker read Zenoh's own FIFO channels instead, so
the receiving thread never touches Python.
"""

from __future__ import annotations

import os
import queue
import time
from collections.abc import Callable
from typing import Generic, TypeVar

import zenoh

T = TypeVar("T")

#: The GIL switch interval of a process that polls. A thread that puts into the Inbox's queue (a query's
#: callback, a timer) needs the GIL, which the poller keeps taking back; at Python's default interval (5 ms) it
#: can wait that long. 20 us gave the fastest round trips (docs/benchmarks.md, polling). It is the process's:
#: its entry point sets it when its settings poll (services/process.py, ``configure_process``), not the inbox.
POLLING_SWITCH_INTERVAL_S = 2e-5


def poll_seconds(poll_ms: float) -> float:
    """Check ``poll_ms`` and return it in seconds. A positive one pays only with the process's switch interval
    shortened to :data:`POLLING_SWITCH_INTERVAL_S`, which the entry point does (services/process.py)."""
    if poll_ms < 0:
        raise ValueError(f"poll_ms must be >= 0 (0: block at once), got {poll_ms}")
    return poll_ms / 1e3


#: A polling Inbox's naps once its poll time has run out: a Zenoh channel cannot wake a thread sleeping on
#: another source, so it looks again after 50 us, then after twice as long each time, up to 1 ms.
NAP_MIN_S = 5e-5
NAP_MAX_S = 1e-3
#: Messages a polling Inbox's channel holds per subscriber before Zenoh's thread waits for the worker.
CHANNEL_CAPACITY = 256


class Inbox(Generic[T]):
    """The messages of a lock-step worker: Zenoh samples, turned into items, and items put by other threads.

    ``poll_s`` 0 (blocking): each subscriber's callback puts its item into a queue, and :meth:`get` sleeps on
    that queue. ``poll_s`` > 0 (polling): each subscriber delivers into a Zenoh FIFO channel that the worker
    reads itself with ``try_recv``, so the Zenoh thread that received the sample never waits for the GIL the
    poller holds. The sim and the learner's link reading them this way, against both handing over through
    callbacks, side by side in single runs: 12 to 32% more lock-step steps a second (docs/benchmarks.md).
    :meth:`get` looks at every channel and then the queue, yielding the CPU between rounds, for ``poll_s``;
    then it naps (:data:`NAP_MIN_S` to :data:`NAP_MAX_S`), since it has no single thing to sleep on.

    Samples already in a channel come before the queue's items, so an item put after them (the sim's stop)
    finds them taken. Each subscriber's samples keep their order.
    """

    def __init__(self, poll_s: float) -> None:
        self._poll_s = poll_s
        self._queue: queue.Queue[T] = queue.Queue()
        self._channels: list[tuple[zenoh.Subscriber, Callable[[zenoh.Sample], T]]] = []

    def put(self, item: T) -> None:
        """From any thread: a message that does not come through a subscriber (a query, a timer's verdict)."""
        self._queue.put(item)

    def subscribe(self, session: zenoh.Session, key: str, to_item: Callable[[zenoh.Sample], T]) -> zenoh.Subscriber:
        """Declare a subscriber on ``key`` whose samples reach :meth:`get` as ``to_item(sample)``."""
        if self._poll_s <= 0:
            return session.declare_subscriber(key, lambda sample: self._queue.put(to_item(sample)))
        subscriber = session.declare_subscriber(key, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        self._channels.append((subscriber, to_item))
        return subscriber

    def get(self, timeout: float) -> T:
        """The next message, waited for up to ``timeout`` seconds (0: only what is there now); raises
        queue.Empty when none comes, as ``Queue.get`` does."""
        if self._poll_s <= 0:
            return self._queue.get(timeout=timeout)
        start = time.perf_counter()
        nap = NAP_MIN_S
        while True:
            for subscriber, to_item in self._channels:
                sample = subscriber.try_recv()
                if sample is not None:
                    return to_item(sample)
            try:
                return self._queue.get_nowait()
            except queue.Empty:
                pass
            waited = time.perf_counter() - start
            if waited >= timeout:
                raise queue.Empty
            if waited < self._poll_s:
                os.sched_yield()
            else:
                time.sleep(min(nap, timeout - waited))
                nap = min(2 * nap, NAP_MAX_S)
