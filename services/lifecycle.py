"""Lifetimes: what an object owns closed with it, a service run until SIGTERM/SIGINT and then drained, and
stopped when its launcher is gone."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from functools import cached_property
from typing import Any, Self

log = logging.getLogger(__name__)

#: Set by services.procs.ProcessGroup to its own pid in every process it starts.
LAUNCHER_PID_ENV = "SWIMM_LAUNCHER_PID"


class Owner:
    """Closes what it owns (a session, the subscribers, queryables and publishers declared on it) with itself.

    Each goes on ``resources`` as it is made, and ``close()``, or the end of a ``with`` block of the owner, closes
    them in reverse order, once. What it is lent, such as a caller's session, is not put there: the lender closes it.
    """

    @cached_property
    def resources(self) -> ExitStack:
        return ExitStack()

    def close(self) -> None:
        self.resources.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Service(Owner):
    """A service: ``start()`` declares what it serves, ``close()`` stops it; a ``with`` block of it is its life."""

    def start(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        try:
            self.start()
        except BaseException:
            self.close()  # what it opened before it failed
            raise
        return self


def serve_until_signalled(service: Service, stop_event: threading.Event | None = None) -> None:
    """Start ``service``, block until SIGTERM or SIGINT (or ``stop_event``), then stop it cleanly."""
    stop_event = stop_event or threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop_event.set())
    with service:
        stop_event.wait()


@contextmanager
def stop_on_signals(event: threading.Event, then: str, second_ctrl_c_interrupts: bool = False) -> Iterator[None]:
    """While inside, SIGTERM and SIGINT set ``event`` (and log ``then``, what happens next) instead of killing.

    With ``second_ctrl_c_interrupts`` a second Ctrl-C raises KeyboardInterrupt, for work that may hang
    in its clean-up. Off the main thread (where Python cannot install handlers) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def request_stop(signum: int, _frame: Any) -> None:
        if event.is_set() and signum == signal.SIGINT and second_ctrl_c_interrupts:
            raise KeyboardInterrupt
        log.info("%s received: %s", signal.Signals(signum).name, then)
        event.set()

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """While inside, SIGTERM raises KeyboardInterrupt, so a job stopped by ``kill``, systemd or ``docker stop``
    ends as Ctrl-C ends it (a background job started from a script ignores SIGINT, so SIGTERM is how it is
    stopped). Off the main thread it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stop_when_launcher_exits(period_s: float = 1.0) -> None:
    """In a process that a ProcessGroup started, send this process SIGTERM once its launcher is gone.

    A launcher that is killed outright (SIGKILL, a crash, the OOM killer) cannot stop its services in order, and
    they would otherwise live on, holding ports and cores; each then stops as on Ctrl-C (a learner saves).
    Nothing happens in a process started any other way.
    """
    variable = os.environ.get(LAUNCHER_PID_ENV, "")
    launcher = int(variable) if variable.isdigit() else None
    if launcher is None or os.getppid() != launcher:
        return  # not started by a ProcessGroup, or started by one that is already gone

    def watch() -> None:
        while os.getppid() == launcher:
            time.sleep(period_s)
        log.warning("the launcher (pid %d) is gone: stopping", launcher)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="launcher-watch", daemon=True).start()
