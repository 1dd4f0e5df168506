"""A training run's folder: the names of its files, and the live numbers `swimm up` and watchers read from it.

The learner writes its progress as a small JSON file rather than a Zenoh topic: the run folder already exists,
a finished run keeps its last numbers, and a watcher needs no session. Kept free of heavy imports so that
`swimm up`, `swimm eval --watch` and benchmarks name the files from here instead of copying the names.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

PROGRESS_FILE = "progress.json"
BEST_MODEL = "best_model.zip"  # the evaluation callback's best model so far
BEST_MODEL_SCORE = "best_model.json"  # its evaluation, with the zip's SHA-256
EVALUATIONS_CSV = "evaluations.csv"  # one row per evaluation
FINAL_MODEL = "final_model.zip"  # the model as training ended
LIVE_MODEL = "final_model_live.zip"  # with --actor-average: the learner's own weights as training ended, to resume
DEMOS_FILE = "demonstrations.npz"  # the scripted tracker's demonstrations, for a resumed run's cloning loss
LEARN_CONFIG = "learn.yaml"  # the settings `swimm up` handed to its learner


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


def latest_evaluation(run_dir: Path) -> tuple[int, float] | None:
    """(steps, mean return) of the run's newest evaluation, or None before the first."""
    try:
        lines = (run_dir / EVALUATIONS_CSV).read_text().splitlines()
    except OSError:
        return None
    if len(lines) < 2:
        return None
    row = dict(zip(lines[0].split(","), lines[-1].split(","), strict=False))
    try:
        return int(row["num_timesteps"]), float(row["mean_return"])
    except (KeyError, ValueError):  # a row being written
        return None


def progress_postfix(snapshot: dict[str, Any], evaluation: tuple[int, float] | None = None) -> dict[str, Any]:
    """The short numbers a progress bar shows beside itself (`swimm learn` and `swimm up` alike)."""
    mean = snapshot.get("mean_recent_return")
    postfix = {
        "ep": snapshot.get("episodes", 0),
        "ret": "n/a" if mean is None else f"{mean:.0f}",
        "steps/s": f"{snapshot.get('env_steps_per_s', 0.0):.0f}",
    }
    if evaluation is not None:
        postfix["eval"] = f"{evaluation[1]:.0f}@{evaluation[0]}"
    return postfix
