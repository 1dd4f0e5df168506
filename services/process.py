"""Process-wide settings, set once by a process's entry point and logged once.

Three settings belong to the whole process rather than to an object in it, and each must be in place before the
first thing that reads it:

- the GIL switch interval (``sys.setswitchinterval``), shortened when the process polls an inbox
  (services/polling.py: a polling worker keeps taking the GIL back from the threads that hand it messages);
- ``ZENOH_RUNTIME``, Zenoh's thread pools, which Zenoh reads when the process opens its first session
  (services/session.py, ``--zenoh-threads``), so a later session shares whatever the first one found. By default
  each of Zenoh's five runtimes has its own pool, and one received message wakes two or three of their threads;
  on two cores they preempt the lock-step worker that steps the World, and each wake-up costs CPU the pipeline
  needs (docs/benchmarks.md, one Zenoh thread). A positive ``zenoh_threads`` hands all five to one pool;
- ``LP_NUM_THREADS``, Mesa llvmpipe's rasteriser threads, which Mesa reads when the process makes its first GL
  context (sim_service/world.py, ``render_threads``). By default it starts one per core; a 64 px frame is too
  small to share out, so 0 (draw on the calling thread) renders faster on a CPU (docs/physics.md). A GPU's EGL
  driver ignores the variable.

Library code (links, responders, sessions, the World) never sets them: `swimm`'s main (swimm/cli.py) calls
:func:`configure_process` with :meth:`ProcessSettings.of` its command's settings before the command runs, and any
other entry point (``python -m bench.sim``, a test's fixture) calls it itself. Code that builds those objects
without it runs with Python's, Zenoh's and Mesa's defaults (or whatever the environment says).

The processes this one starts see the environment it was started with (:func:`child_environment`): each swimm
process chooses for itself from its own settings, and a user's own ``ZENOH_RUNTIME`` or ``LP_NUM_THREADS`` is
passed on as it was.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
from collections.abc import Mapping
from typing import Any

from services.polling import POLLING_SWITCH_INTERVAL_S

log = logging.getLogger(__name__)

#: Zenoh reads its runtimes' thread pools from this environment variable when a process opens its first session.
ZENOH_RUNTIME_VARIABLE = "ZENOH_RUNTIME"
#: Mesa's llvmpipe reads its number of rasteriser threads from this one when a process makes its first GL context.
RENDER_THREADS_VARIABLE = "LP_NUM_THREADS"
#: ``WorldSettings.render_threads``'s default (0: draw on the stepping thread), for commands that render a World
#: whose settings are not among theirs (in-process envs of `swimm learn`, `swimm eval`, `swimm bench`).
DEFAULT_RENDER_THREADS = 0

#: The value each variable had before this process set it (None: unset), for the processes it starts.
_ENVIRONMENT_BEFORE: dict[str, str | None] = {}


def zenoh_runtime(threads: int) -> str:
    """The ``ZENOH_RUNTIME`` that hands Zenoh's five runtimes (application, acceptor, tx, rx, network) over to one
    pool of ``threads`` worker threads."""
    return (
        f"(app: (worker_threads: {threads}), acc: (handover: app), tx: (handover: app), rx: (handover: app), "
        "net: (handover: app))"
    )


@dataclasses.dataclass(frozen=True)
class ProcessSettings:
    """What a process sets for itself, read from its settings."""

    poll_ms: float = 0.0  # the longest any of its inboxes polls; > 0 shortens the GIL switch interval
    zenoh_threads: int = 0  # Zenoh's worker threads, one pool for all runtimes; 0: Zenoh's pool per runtime
    render_threads: int | None = None  # Mesa llvmpipe's threads; -1: Mesa's default; None: the process does not render

    @classmethod
    def of(cls, settings: Any, renders: bool = False) -> ProcessSettings:
        """The process settings of a command's settings: the first ``zenoh_threads`` and ``render_threads`` and the
        largest ``poll_ms`` in its tree of dataclasses. ``renders``: the command may render a World whose settings
        are not in the tree, with :data:`DEFAULT_RENDER_THREADS` unless the tree says otherwise."""
        found: dict[str, list[Any]] = {"poll_ms": [], "zenoh_threads": [], "render_threads": []}

        def walk(node: Any) -> None:
            if not dataclasses.is_dataclass(node) or isinstance(node, type):
                return
            for field in dataclasses.fields(node):
                value = getattr(node, field.name)
                if field.name in found and isinstance(value, (int, float)) and not isinstance(value, bool):
                    found[field.name].append(value)
                walk(value)

        walk(settings)
        render_threads = found["render_threads"][0] if found["render_threads"] else None
        if render_threads is None and renders:
            render_threads = DEFAULT_RENDER_THREADS
        return cls(
            poll_ms=max(found["poll_ms"], default=0.0),
            zenoh_threads=found["zenoh_threads"][0] if found["zenoh_threads"] else 0,
            render_threads=render_threads,
        )


def _set_variable(name: str, value: str) -> None:
    _ENVIRONMENT_BEFORE.setdefault(name, os.environ.get(name))
    os.environ[name] = value


def configure_process(process: ProcessSettings, role: str = "process", level: int = logging.INFO) -> list[str]:
    """Set the process-wide settings ``process`` asks for, and say so in one line (at ``level``: a command whose
    output is its answer says it only at DEBUG); returns what was set.

    Call it once, from the entry point, before the process opens a Zenoh session or renders. Refuses (ValueError)
    a negative poll time or thread count, naming its flag.
    """
    if process.poll_ms < 0:
        raise ValueError(f"poll_ms must be >= 0 (0: block at once), got {process.poll_ms}")
    if process.zenoh_threads < 0:
        raise ValueError(f"--zenoh-threads must be >= 0 (0: Zenoh's pool per runtime), got {process.zenoh_threads}")
    done: list[str] = []
    if process.poll_ms > 0:
        sys.setswitchinterval(min(sys.getswitchinterval(), POLLING_SWITCH_INTERVAL_S))
        done.append(
            f"GIL switch interval {sys.getswitchinterval() * 1e6:g} us (it polls its inbox for {process.poll_ms:g} ms, "
            "and the threads that hand it messages need the GIL)"
        )
    if process.zenoh_threads > 0:
        if ZENOH_RUNTIME_VARIABLE in os.environ and ZENOH_RUNTIME_VARIABLE not in _ENVIRONMENT_BEFORE:
            done.append(f"Zenoh's threads as {ZENOH_RUNTIME_VARIABLE} says (set before it started; it wins)")
        else:
            _set_variable(ZENOH_RUNTIME_VARIABLE, zenoh_runtime(process.zenoh_threads))
            done.append(
                f"{ZENOH_RUNTIME_VARIABLE}: Zenoh on one pool of {process.zenoh_threads} worker thread(s) "
                "(--zenoh-threads; fewer wake-ups per message)"
            )
    if process.render_threads is not None and process.render_threads >= 0:
        _set_variable(RENDER_THREADS_VARIABLE, str(process.render_threads))
        why = "Mesa draws on the rendering thread: faster for small frames" if process.render_threads == 0 else ""
        done.append(f"{RENDER_THREADS_VARIABLE}={process.render_threads} (render_threads{'; ' + why if why else ''})")
    if done:
        log.log(level, "%s process settings: %s", role, "; ".join(done))
    return done


def child_environment(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """``environ`` (default: this process's) with each variable :func:`configure_process` set back to what it was
    before: the environment for a process this one starts, which configures itself from its own settings."""
    child = dict(os.environ if environ is None else environ)
    for name, before in _ENVIRONMENT_BEFORE.items():
        if before is None:
            child.pop(name, None)
        else:
            child[name] = before
    return child
