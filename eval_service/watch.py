"""`swimm eval --watch RUN_DIR`: score every new best model a training run saves, beside the training.

The learner's evaluation callback saves ``best_model.zip`` and then ``best_model.json`` (its score, step
count and the zip's SHA-256), each written aside and renamed into place, so either file is always whole. The
watcher polls the JSON: a new ``num_timesteps`` there means a new zip. It copies the zip first (the learner
may replace it at any time) and keeps the copy only if its hash is the one the JSON gives: a zip replaced
after the JSON was read belongs to the next JSON, and is taken at the next poll. It evaluates the copy on its
own claimed eval env (released between evaluations), writes one run folder per checkpoint and publishes each
summary on the metrics key. It stops when the run writes ``result.json`` (training over) and the last best
model is scored, or on SIGTERM / Ctrl-C.

The algorithm, observation mode, reward and task come from the run's ``settings.json`` (a policy must be evaluated
on what it was trained on); ``--algo`` overrides the algorithm for runs without one.
"""

from __future__ import annotations

import csv
import json
import logging
import shutil
import signal
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

from eval_service.engine import EvaluationSettings, evaluate
from eval_service.live import LiveFeed
from eval_service.publish import ResultPublisher
from learner_service.evaluation import Contender
from learner_service.progress import BEST_MODEL, BEST_MODEL_SCORE
from services.results import file_sha256

log = logging.getLogger(__name__)

RUN_SETTINGS = "settings.json"
RUN_FINISHED = "result.json"
WATCH_TABLE = "watch.csv"


def best_model_version(run_dir: Path) -> tuple[int, str | None] | None:
    """The ``num_timesteps`` of the saved best model and its zip's SHA-256 (None from runs that did not record
    it), or None while there is none (or its JSON is unreadable)."""
    try:
        score = json.loads((run_dir / BEST_MODEL_SCORE).read_text())
        return int(score["num_timesteps"]), score.get("model_sha256")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def run_settings(run_dir: Path) -> dict[str, Any]:
    """The training run's own settings (algo, obs, reward, task), from its settings.json; {} if it has none yet."""
    try:
        return dict(json.loads((run_dir / RUN_SETTINGS).read_text()).get("settings", {}))
    except (OSError, ValueError):
        return {}


class BestModelWatcher:
    """Yields a private copy of each new best model of ``run_dir``, once per saved version."""

    def __init__(self, run_dir: Path, copies: Path) -> None:
        self.run_dir = run_dir
        self.copies = copies
        self.seen: int | None = None

    def poll(self) -> tuple[int, Path] | None:
        found = best_model_version(self.run_dir)
        if found is None or found[0] == self.seen:
            return None
        version, sha256 = found
        self.copies.mkdir(parents=True, exist_ok=True)
        copy = self.copies / f"best-{version}.zip"
        shutil.copyfile(self.run_dir / BEST_MODEL, copy)
        # A newer zip than the JSON read above: its own JSON follows, and the next poll takes it.
        replaced = file_sha256(copy) != sha256 if sha256 else best_model_version(self.run_dir) != found
        if replaced:
            copy.unlink()
            return None
        self.seen = version
        return version, copy

    @property
    def finished(self) -> bool:
        return (self.run_dir / RUN_FINISHED).is_file()


def watch(settings: EvaluationSettings, run_dir: Path, out: Path, feed: LiveFeed | None,
          publisher: ResultPublisher | None, interval_s: float = 5.0,
          stop: threading.Event | None = None) -> int:  # fmt: skip
    """Evaluate each new best model until the run finishes (or ``stop`` is set), looking every ``interval_s``;
    returns how many were scored."""
    stop = stop or _stop_on_signals()
    watcher = BestModelWatcher(run_dir, out / "checkpoints")
    scored = 0
    log.info("watching %s for new best models (every %.1f s)", run_dir, interval_s)
    while not stop.is_set():
        finished = watcher.finished  # read before polling, so the last model saved before result.json is scored
        found = watcher.poll()
        if found is not None:
            version, copy = found
            trained = run_settings(run_dir)
            algo = trained.get("algo") or (settings.algo[0] if settings.algo else "sac")
            evaluated = replace(settings, **{name: trained.get(name, getattr(settings, name))
                                             for name in ("obs", "reward", "task")})  # fmt: skip
            entry = Contender(f"{algo}@{version}", algo, str(copy))
            summaries = evaluate(evaluated, out / f"step-{version}", [entry], feed, publisher,
                                 about={"watched_run": str(run_dir), "num_timesteps": version})  # fmt: skip
            _append(out / WATCH_TABLE, version, summaries[entry.label])
            scored += 1
        elif finished:
            log.info("%s finished training; %d best models scored", run_dir, scored)
            break
        stop.wait(interval_s)
    return scored


def _append(path: Path, version: int, summary: dict[str, float]) -> None:
    new = not path.is_file()
    with path.open("a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["num_timesteps", *summary])
        if new:
            writer.writeheader()
        writer.writerow({"num_timesteps": version, **summary})


def _stop_on_signals() -> threading.Event:
    """An event SIGTERM sets (the CLI turns Ctrl-C into a clean exit already); main thread only."""
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    return stop
