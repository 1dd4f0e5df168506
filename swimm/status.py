"""`swimm status`: who is live in a namespace and what each is doing, like `docker compose ps`.

Three looks at the network, all read-only:

- the liveliness tokens under ``<ns>/@live/**``: every sim, encoder, learner and evaluator holding a session;
  the several a process may hold (a learner claims its train and eval envs under two ids) count as one row;
- the numbers sims, encoders and learners publish on ``<ns>/metrics/**`` every 2 s, listened to for ``window_s``
  so that two snapshots give a rate (steps/s, images/s) and the newest one a last-seen age; a learner's say what
  it is doing (its phase and that phase's count, steps, latest evaluation);
- the ``info`` of every env (``<ns>/*/*/ctl``): its sim, who holds it, its episode and step.

With no router answering within ``--wait-s`` it says so in one line and exits 1.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import msgpack
import zenoh

from services.control import survey
from services.keys import Keys
from services.presence import live_tokens, process_of
from services.session import StartupTimeout, build_config, describe_endpoints, open_session
from services.settings import NonNegFloat, PosFloat, ZenohSettings, check_ranges

RATE_COUNTERS = {
    "sim": ("steps", "steps/s"),
    "encoder": ("images", "images/s"),
    "learner": ("num_timesteps", "steps/s"),
}


@dataclass
class StatusSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    json: bool = False  # print one JSON object instead of tables
    window_s: PosFloat = 4.5  # seconds to listen to the services' metrics (published every 2 s: two give a rate)
    wait_s: NonNegFloat = 2.0  # seconds to wait for a router to answer (replaces --startup-timeout-s)


def check(settings: StatusSettings) -> None:
    check_ranges(settings)


def live_processes(session: zenoh.Session, keys: Keys) -> dict[tuple[str, str], list[str]]:
    """The ids of the liveliness tokens in the namespace, by (role, process) (:func:`services.presence.process_of`)."""
    processes: dict[tuple[str, str], list[str]] = {}
    for role, ident in sorted(live_tokens(session, keys.live_role("*"))):
        processes.setdefault((role, process_of(ident)), []).append(ident)
    return processes


def listen_to_metrics(session: zenoh.Session, keys: Keys, window_s: float) -> dict[tuple[str, str], list[dict]]:
    """Every metrics snapshot published during ``window_s``, per (role, id), oldest first."""
    snapshots: dict[tuple[str, str], list[dict]] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            body = msgpack.unpackb(sample.payload.to_bytes())
        except (ValueError, msgpack.UnpackException):
            return  # not ours to judge here; the publisher's own logs say more
        if isinstance(body, dict) and "role" in body and "id" in body:
            with lock:
                snapshots.setdefault((str(body["role"]), str(body["id"])), []).append(body)

    subscriber = session.declare_subscriber(keys.all_metrics(), on_sample)
    try:
        time.sleep(window_s)
    finally:
        subscriber.undeclare()
    with lock:
        return {key: list(values) for key, values in snapshots.items()}


def rate(snapshots: list[dict], counter: str) -> float | None:
    """``counter``'s increase per second between the first and the newest snapshot; None with fewer than two."""
    if len(snapshots) < 2:
        return None
    first, last = snapshots[0], snapshots[-1]
    elapsed = float(last["t"]) - float(first["t"])
    if elapsed <= 0:
        return None
    return (float(last.get(counter, 0)) - float(first.get(counter, 0))) / elapsed


def gather(settings: StatusSettings, session: zenoh.Session) -> dict[str, Any]:
    """The namespace's services and envs, as ``swimm status --json`` prints them."""
    keys = Keys(settings.zenoh.namespace)
    members = live_processes(session, keys)
    metrics = listen_to_metrics(session, keys, settings.window_s)
    now = time.time()
    services = []
    for role, ident in sorted(set(members) | set(metrics)):
        snapshots = metrics.get((role, ident), [])
        entry: dict[str, Any] = {"role": role, "id": ident, "live": (role, ident) in members}
        if len(members.get((role, ident), [])) > 1:
            entry["members"] = members[(role, ident)]
        if snapshots:
            entry["last_seen_s"] = round(now - float(snapshots[-1]["t"]), 1)
            counter, unit = RATE_COUNTERS.get(role, (None, None))
            value = rate(snapshots, counter) if counter else None
            if value is not None:
                entry["rate"], entry["rate_unit"] = round(value, 1), unit
            entry["counters"] = {k: v for k, v in snapshots[-1].items() if k not in ("role", "id", "t")}
            if doing := what_it_does(entry["counters"]):
                entry["doing"] = doing
        services.append(entry)
    infos = survey(session, f"{keys.namespace}/*/*/ctl", timeout_s=2.0)
    infos.sort(key=lambda info: (info.channel, info.env.zfill(6), info.sim))
    envs = [{key: getattr(info, key) for key in ("channel", "env", "sim", "holder", "ep", "seq")} for info in infos]
    return {"namespace": keys.namespace, "services": services, "envs": envs}


def what_it_does(counters: dict[str, Any]) -> str:
    """A learner's phase with its count, and its latest evaluation (``training 1200/20000, eval 310@1000``); ""
    for a service that publishes no phase."""
    if "phase" not in counters:
        return ""
    doing = f"{counters['phase']} {counters.get('phase_done', 0)}/{counters.get('phase_total', '?')}"
    if "eval_return" in counters:
        doing += f", eval {counters['eval_return']:.0f}@{counters['eval_timesteps']}"
    return doing


def format_status(status: dict[str, Any]) -> str:
    """Two plain tables: the services (one row per process), then the envs."""
    lines = [f"namespace {status['namespace']}", ""]
    rows = [("ROLE", "ID", "LIVE", "LAST SEEN", "RATE", "DOING")]
    for entry in status["services"]:
        seen = f"{entry['last_seen_s']:.1f} s ago" if "last_seen_s" in entry else "-"
        rated = f"{entry['rate']:.1f} {entry['rate_unit']}" if "rate" in entry else "-"
        live = "yes" if entry["live"] else "no"
        rows.append((entry["role"], entry["id"], live, seen, rated, entry.get("doing", "-")))
    lines += _table(rows)
    if status["envs"]:
        lines.append("")
        rows = [("ENV", "SIM", "HELD BY", "EPISODE", "STEP")]
        for env in status["envs"]:
            holder = env["holder"] or "free"
            rows.append((f"{env['channel']}/{env['env']}", str(env["sim"]), holder, str(env["ep"]), str(env["seq"])))
        lines += _table(rows)
    return "\n".join(lines) + "\n"


def _table(rows: list[tuple[str, ...]]) -> list[str]:
    widths = [max(len(str(row[i])) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(str(cell).ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip() for row in rows]


def run(settings: StatusSettings) -> int:
    """Print the status; exit 1, saying where it looked in one line, when no router or nothing in the namespace
    answers."""
    check(settings)
    # A query's output is its answer: the session's own lines (waiting, joined) only at DEBUG.
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        logging.getLogger("services.session").setLevel(logging.WARNING)
    zenoh_settings = dataclasses.replace(settings.zenoh, startup_timeout_s=settings.wait_s)
    try:
        session = open_session(zenoh_settings, role="status")
    except StartupTimeout:
        where = describe_endpoints(build_config(zenoh_settings))
        sys.stderr.write(
            f"no Zenoh router answered at {where} within {settings.wait_s:g} s: is `swimm up` (or `swimm router`) "
            "running there? (--connect names another, --wait-s waits longer)\n"
        )
        return 1
    with session:
        status = gather(settings, session)
    if settings.json:
        sys.stdout.write(json.dumps(status) + "\n")
    else:
        sys.stdout.write(format_status(status))
    if not status["services"] and not status["envs"]:
        where = describe_endpoints(build_config(settings.zenoh))
        sys.stderr.write(
            f"nothing live in namespace {settings.zenoh.namespace} (connected to {where}); is `swimm up` (or a sim) "
            "running there? Pass the same --connect and --namespace\n"
        )
        return 1
    return 0
