"""`swimm record` and `swimm replay`: :func:`services.record.record` and :func:`services.record.replay` until
Ctrl-C or SIGTERM."""

from __future__ import annotations

import json
import sys
import threading

from services.lifecycle import stop_on_signals
from services.record import RecordSettings, ReplaySettings, record, replay


def run_record(settings: RecordSettings) -> int:
    stop = threading.Event()
    with stop_on_signals(stop, "finishing the recording"):
        summary = record(settings, stop)
    sys.stdout.write(json.dumps(summary) + "\n")
    return 0


def run_replay(settings: ReplaySettings) -> int:
    stop = threading.Event()
    with stop_on_signals(stop, "stopping the replay"):
        replay(settings, stop)
    return 0
