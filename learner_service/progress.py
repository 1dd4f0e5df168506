"""A training run's folder: the names of its files, and the live numbers `swimm up` and watchers read from it.

The learner writes its progress as a small JSON file (and, when distributed, publishes the same numbers for
`swimm status`): the run folder already exists, a finished run keeps its last numbers, and a watcher needs no
session. Kept free of heavy imports so that `swimm up`, `swimm eval --watch` and benchmarks name the files from
here instead of copying the names.

A run goes through :data:`PHASES` in order (the first three only with ``--demo-steps``; evaluations come and go
during training), and the progress names the current one with its own count, so a bar shows "cloning 12/30
epochs" rather than a training bar stuck at zero, and counts training's rate and ETA over training steps only.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

PROGRESS_FILE = "progress.json"
BEST_MODEL = "best_model.zip"  # the evaluation callback's best model so far
BEST_MODEL_SCORE = "best_model.json"  # its evaluation, with the zip's SHA-256
EVALUATIONS_CSV = "evaluations.csv"  # one row per evaluation
FINAL_MODEL = "final_model.zip"  # the model as training ended
LIVE_MODEL = "final_model_live.zip"  # with --actor-average: the learner's own weights as training ended, to resume
DEMOS_FILE = "demonstrations.npz"  # the scripted tracker's demonstrations, for a resumed run's cloning loss
LEARN_CONFIG = "learn.yaml"  # the settings `swimm up` handed to its learner
UP_CONFIG = "up.yaml"  # the settings of a `swimm up` run, for `swimm up --config` to resume it

#: A run's phases, in order, with the unit each counts: the scripted tracker plays demonstrations, the policy
#: clones its actions, the critic alone learns their value, then training, interrupted by evaluations.
PHASES = {
    "demonstrations": "step",
    "cloning": "epoch",
    "critic warm-up": "update",
    "training": "step",
    "evaluation": "episode",
}


def replace_atomically(path: Path, write: Callable[[Path], Any]) -> None:
    """``write`` the new file beside ``path``, then rename it over ``path``: a reader in another process (`swimm up`,
    `swimm eval --watch`) sees the old file or the new one, never half of one."""
    partial = path.with_name(path.name + ".partial")
    write(partial)
    os.replace(partial, path)


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


def progress_postfix(snapshot: dict[str, Any]) -> dict[str, Any]:
    """The short numbers a training bar shows beside itself (`swimm learn` and `swimm up` alike): episodes, recent
    return, and the latest evaluation as return@steps. Its rate is the bar's own: training steps only."""
    mean = snapshot.get("mean_recent_return")
    postfix = {"ep": snapshot.get("episodes", 0), "ret": "n/a" if mean is None else f"{mean:.0f}"}
    if "eval_return" in snapshot:
        postfix["eval"] = f"{snapshot['eval_return']:.0f}@{snapshot['eval_timesteps']}"
    return postfix


def describe_progress(snapshot: dict[str, Any]) -> str:
    """The progress in one log line: ``cloning 12/30 epochs`` or ``training 1200/20000 steps, ep 4, ret 310``."""
    phase = snapshot.get("phase", "training")
    done = snapshot.get("phase_done", snapshot.get("num_timesteps", 0))
    total = snapshot.get("phase_total", snapshot.get("total_timesteps", "?"))
    line = f"{phase} {done}/{total} {PHASES.get(phase, 'step')}s"
    if phase == "training":
        line += "".join(f", {key} {value}" for key, value in progress_postfix(snapshot).items())
        line += f", {snapshot.get('env_steps_per_s', 0.0):.0f} steps/s"
    return line


class RunProgress:
    """What a learner is doing now: its phase with that phase's count, its training numbers and its latest
    evaluation; rewritten to ``progress.json`` at most every ``interval_s`` (and at each change of phase), and
    drawn on ``bar`` if one is given. Without a ``path`` it only keeps the numbers (for a publisher)."""

    def __init__(
        self, path: Path | None = None, total_timesteps: int = 0, interval_s: float = 1.0, bar: PhaseBar | None = None
    ) -> None:
        self.path = path
        self.interval_s = interval_s
        self.bar = bar
        self.numbers: dict[str, Any] = {"num_timesteps": 0, "total_timesteps": total_timesteps}
        self.phase, self.done, self.total = "training", 0, total_timesteps
        self.entered: list[str] = []  # every phase entered, in order: a watcher polling less often misses none
        self.evaluation: tuple[int, float] | None = None
        self._lock = threading.Lock()
        self._written = 0.0

    def start(self, phase: str, total: int, done: int = 0) -> None:
        """Enter ``phase``, which counts ``total`` of its units; shown and written at once."""
        if phase not in PHASES:
            raise ValueError(f"unknown phase {phase!r}; one of {', '.join(PHASES)}")
        with self._lock:
            self.phase, self.done, self.total = phase, done, total
            self.entered.append(phase)
        self._show(force=True)

    def advance(self, done: int) -> None:
        """The current phase's count so far."""
        with self._lock:
            self.done = done
        self._show()

    def update(self, numbers: dict[str, Any], finished: bool = False) -> None:
        """Training's numbers (``EpisodeStatsCallback.snapshot``); while training they are its count too."""
        with self._lock:
            self.numbers = dict(numbers)
            if self.phase == "training":
                self.done = int(numbers["num_timesteps"])
        self._show(force=finished, finished=finished)

    def evaluated(self, num_timesteps: int, mean_return: float) -> None:
        with self._lock:
            self.evaluation = (num_timesteps, mean_return)

    def snapshot(self) -> dict[str, Any]:
        """Training's numbers, the phase (``phase``, ``phase_done``, ``phase_total``), the phases entered so far
        (``phases_entered``) and the latest evaluation."""
        with self._lock:
            snap = self.numbers | {"phase": self.phase, "phase_done": self.done, "phase_total": self.total,
                                   "phases_entered": list(self.entered)}  # fmt: skip
            if self.evaluation is not None:
                snap["eval_timesteps"], snap["eval_return"] = self.evaluation
            return snap

    def _show(self, force: bool = False, finished: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._written < self.interval_s:
            return
        self._written = now
        snap = self.snapshot()
        if self.bar is not None:
            self.bar.show(snap)
        if self.path is not None:
            write_json_atomically(self.path, snap | {"finished": finished})


class PhaseBar:
    """A tqdm bar that names the run's phase and counts that phase's own units. Entering a phase restarts the
    bar's clock at the phase's count, so training's rate and ETA count training steps only (not the minute of
    demonstrations before it, nor the evaluations in between)."""

    def __init__(self, disable: bool = False, file: Any = None) -> None:
        self.disable = disable
        self.file = file
        self.bar: tqdm | None = None  # drawn from the first phase on, not as an empty bar before it
        self.phase: str | None = None

    def show(self, snapshot: dict[str, Any]) -> None:
        phase = snapshot.get("phase", "training")
        done = int(snapshot.get("phase_done", snapshot.get("num_timesteps", 0)))
        if phase != self.phase:
            self.phase = phase
            self.enter(phase, snapshot.get("phase_total", snapshot.get("total_timesteps")) or None, done)
        assert self.bar is not None
        self.bar.update(done - self.bar.n)
        if phase == "training":
            self.bar.set_postfix(progress_postfix(snapshot), refresh=False)
        self.bar.refresh()

    def enter(self, phase: str, total: int | None, done: int) -> None:
        """A new bar for ``phase`` in place of the last one: its name, unit and total, its clock from ``done`` on."""
        if self.bar is not None:
            self.bar.leave = False  # the line is the new phase's now
            self.bar.close()
        self.bar = tqdm(total=total, initial=done, desc=phase, unit=PHASES.get(phase, "step"), disable=self.disable,
                        file=self.file, dynamic_ncols=True, leave=False)  # fmt: skip

    def close(self) -> None:
        """Close the bar, leaving its last line in view."""
        if self.bar is not None:
            self.bar.leave = True
            self.bar.close()
