"""The live numbers of a training run as a small JSON file, written by the learner and read by `swimm up`.

A file rather than a Zenoh topic: the run folder already exists, a finished run keeps its last numbers, and a
watcher needs no session. Kept free of heavy imports so `swimm up` (in services/) can read it.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

PROGRESS_FILE = "progress.json"


def replace_atomically(path: Path, write: Callable[[Path], Any]) -> None:
    """``write`` the new file beside ``path``, then rename it over ``path``: a reader in another process (`swimm up`,
    `swimm eval --watch`) sees the old file or the new one, never half of one."""
    partial = path.with_name(path.name + ".partial")
    write(partial)
    os.replace(partial, path)


def file_sha256(path: Path) -> str:
    """The file's SHA-256 as hex: what ``best_model.json`` records of the zip it scores, so a reader can tell that
    the zip it copied is the one the score belongs to."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_json_atomically(path: Path, data: dict[str, Any]) -> None:
    replace_atomically(path, lambda partial: partial.write_text(json.dumps(data, indent=1)))


def read_progress(run_dir: Path) -> dict[str, Any] | None:
    """The run's latest numbers, or None before the learner wrote any."""
    try:
        return json.loads((run_dir / PROGRESS_FILE).read_text())
    except (OSError, ValueError):
        return None


def progress_postfix(snapshot: dict[str, Any]) -> dict[str, Any]:
    """The short numbers a progress bar shows beside itself (`swimm learn` and `swimm up` alike)."""
    mean = snapshot.get("mean_recent_return")
    return {
        "ep": snapshot.get("episodes", 0),
        "ret": "n/a" if mean is None else f"{mean:.0f}",
        "steps/s": f"{snapshot.get('env_steps_per_s', 0.0):.0f}",
    }
