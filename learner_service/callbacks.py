"""stable-baselines3 callbacks of a training run: the paper's evaluation, episode endings and throughput,
checkpoints, a progress bar, and a graceful stop.

- :class:`RolloutEvalCallback` is the reference's evaluation: only once ``min_steps`` training steps have run,
  and then every ``every`` episodes (or steps), checked at the end of a rollout so a rollout (for SAC with
  ``train_freq: 1 episode``, one episode) is never cut in half. It plays N deterministic episodes on its own
  env (the ``eval`` channel when distributed; no early termination), from the same seed each time so
  evaluations are comparable (:func:`learner_service.evaluation.play_episodes`, as `swimm eval` plays them),
  and keeps ``best_model.zip`` with its score and Table 12 metrics in ``best_model.json``.
- :class:`EpisodeStatsCallback` counts how training episodes ended (distance, visibility, collision, time
  limit) and the env-steps per second, for TensorBoard, the log and the run's progress (``progress.json``, the
  bar, `swimm status`: :class:`learner_service.progress.RunProgress`).
- :class:`CheckpointCallback` is SB3's, keeping only the newest replay buffer beside its model (a SAC buffer
  is tens of MB each time).
- :class:`StopOnEvent` ends training when a signal sets an event.
"""

from __future__ import annotations

import csv
import json
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common import callbacks as sb3_callbacks
from stable_baselines3.common.callbacks import BaseCallback

from learner_service.evaluation import play_episodes
from learner_service.learn_settings import EvalSettings
from learner_service.metrics import VERTICAL_ROW_FIELDS, summarise
from learner_service.progress import (
    BEST_MODEL,
    BEST_MODEL_SCORE,
    EVALUATIONS_CSV,
    RunProgress,
    replace_atomically,
    write_json_atomically,
)
from learner_service.registry import SB3Policy
from learner_service.task import CAUSE_COLLISION, CAUSE_DISTANCE, CAUSE_VISIBILITY
from services.results import file_sha256

log = logging.getLogger(__name__)

CAUSE_TIME_LIMIT = "time_limit"  # what an episode that ended with an empty ``info["cause"]`` ran into
CAUSES = (CAUSE_DISTANCE, CAUSE_VISIBILITY, CAUSE_COLLISION, CAUSE_TIME_LIMIT)
#: Table 12 as an evaluation logs it and writes it to evaluations.csv.
EVAL_METRICS = ("mean_return", "std_return", "A", "D", "A'", "D'", "C'", "S_D", "S_A")


def recorded_metrics(summary: dict[str, float]) -> tuple[str, ...]:
    """What an evaluation records of its summary: Table 12, and E when it is the 3d task's."""
    return EVAL_METRICS + tuple(name for name in VERTICAL_ROW_FIELDS if name in summary)


def ending_of(info: dict[str, Any]) -> str:
    """How an episode ended, from its last step's info: the violated condition, or the time limit."""
    return str(info.get("cause") or CAUSE_TIME_LIMIT)


# --- evaluation --------------------------------------------------------------------------------------


class RolloutEvalCallback(BaseCallback):
    """The paper's evaluation during training (see the module docstring); saves the best model to ``save_dir``."""

    def __init__(
        self,
        eval_env: gym.Env,
        settings: EvalSettings,
        save_dir: str | Path,
        verbose: int = 0,
        started: float | None = None,
        acting: Callable[[], AbstractContextManager] = nullcontext,
        progress: RunProgress | None = None,
    ) -> None:
        """``started``: the ``time.perf_counter()`` the rows' ``wall_s`` count from (default: when training starts);
        ``acting``: a context the evaluation and the best model's save run in (averaging.py swaps weights in);
        ``progress``: the run's, which shows the evaluation as a phase of its own."""
        super().__init__(verbose)
        self.acting = acting
        self.progress = progress or RunProgress()
        settings.check()
        self.started = started
        self.eval_env = eval_env
        self.settings = settings
        self.save_dir = Path(save_dir)
        self.best_mean_return = -np.inf
        self.evaluations = 0
        self._episodes_since = 0
        self._steps_at_last = 0

    def _init_callback(self) -> None:
        self.save_dir.mkdir(parents=True, exist_ok=True)
        self._steps_at_last = self.num_timesteps
        if self.started is None:
            self.started = time.perf_counter()
        score = self.save_dir / BEST_MODEL_SCORE
        if score.is_file():  # a resumed run must beat the best it already saved, not overwrite it
            self.best_mean_return = float(json.loads(score.read_text())["mean_return"])

    def _on_step(self) -> bool:
        self._episodes_since += int(np.sum(self.locals["dones"]))
        return True

    @property
    def due(self) -> bool:
        if self.num_timesteps < self.settings.min_steps:
            return False
        if self.settings.unit == "episodes":
            return self._episodes_since >= self.settings.every
        return self.num_timesteps - self._steps_at_last >= self.settings.every

    def _on_rollout_end(self) -> None:
        if self.due:
            self.evaluate()

    def evaluate(self) -> dict[str, float]:
        """Play the evaluation episodes now; log, record, and save the model if it is the best so far."""
        with self.acting():
            return self._evaluate()

    def _evaluate(self) -> dict[str, float]:
        started = time.perf_counter()
        wall_s = started - self.started  # the training time this evaluation's model cost, not its own
        training = self.progress.total
        self.progress.start("evaluation", self.settings.episodes)
        rows = play_episodes(SB3Policy(self.model), self.eval_env, "eval", self.settings.episodes, self.settings.seed,
                             on_episode=lambda row: self.progress.advance(row["episode"]))  # fmt: skip
        summary = summarise(rows)
        violations = Counter(row["first_cause"] or "none" for row in rows)  # each episode's first violation
        self.evaluations += 1
        self._episodes_since = 0
        self._steps_at_last = self.num_timesteps
        for key in recorded_metrics(summary):
            self.logger.record(f"eval/{key}", summary[key])
        self.logger.record("eval/mean_ep_length", float(np.mean([row["steps"] for row in rows])))
        self._append_row(summary, rows, wall_s)
        self.progress.evaluated(self.num_timesteps, summary["mean_return"])
        self.progress.start("training", training, self.num_timesteps)
        is_best = summary["mean_return"] > self.best_mean_return
        log.info(
            "evaluation %d at %d steps: mean return %.1f +- %.1f over %d episodes (first violations %s) in %.1f s%s",
            self.evaluations,
            self.num_timesteps,
            summary["mean_return"],
            summary["std_return"],
            len(rows),
            dict(violations),
            time.perf_counter() - started,
            ", new best model" if is_best else "",
        )
        if is_best:
            self.best_mean_return = summary["mean_return"]
            replace_atomically(self.save_dir / BEST_MODEL, self.model.save)  # `swimm eval --watch` copies it any time
            score = {"num_timesteps": self.num_timesteps, "evaluation": self.evaluations, **summary}
            score["model_sha256"] = file_sha256(self.save_dir / BEST_MODEL)
            score["seed"], score["first_violations"] = self.settings.seed, dict(violations)
            write_json_atomically(self.save_dir / BEST_MODEL_SCORE, score)
        return summary

    def _append_row(self, summary: dict[str, float], rows: list[dict[str, Any]], wall_s: float) -> None:
        path = self.save_dir / EVALUATIONS_CSV
        metrics = recorded_metrics(summary)
        fields = ["num_timesteps", "wall_s", *metrics, "returns"]
        new_file = not path.is_file()
        if not new_file:  # a resumed run's file keeps its own columns (an older one may lack wall_s)
            with path.open(newline="") as handle:
                fields = next(csv.reader(handle), fields)
        with path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
            if new_file:
                writer.writeheader()
            returns = " ".join(f"{row['return']:.3f}" for row in rows)
            row = {"num_timesteps": self.num_timesteps, "wall_s": round(wall_s, 1), "returns": returns}
            row |= {key: summary[key] for key in metrics}
            writer.writerow(row)


# --- episode endings and throughput -----------------------------------------------------------------


class EpisodeStatsCallback(BaseCallback):
    """Counts training episodes by ending and measures env-steps/s; TensorBoard, log lines and ``progress.json``.

    TensorBoard gets ``episodes/<ending>`` (cumulative counts) and ``time/env_steps_per_s`` at each rollout's
    end. ``log_interval_s`` spaces the log lines; ``progress`` (the run's, if given) gets the same numbers at
    every step, and enters the training phase when training starts.
    """

    def __init__(
        self,
        total_timesteps: int,
        log_interval_s: float = 30.0,
        progress: RunProgress | None = None,
        reward_window: int = 20,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        self.total_timesteps = total_timesteps
        self.log_interval_s = log_interval_s
        self.progress = progress or RunProgress()
        self.endings: Counter[str] = Counter({cause: 0 for cause in CAUSES})
        self.recent_returns: deque[float] = deque(maxlen=reward_window)
        self.episodes = 0
        self._start_steps = 0
        self._start_time = 0.0
        self._last_log = 0.0

    def _on_training_start(self) -> None:
        self._start_steps = self.num_timesteps
        self._start_time = self._last_log = time.perf_counter()
        self.progress.update(self.snapshot())
        self.progress.start("training", self.total_timesteps, self.num_timesteps)

    @property
    def steps_per_s(self) -> float:
        """Env steps per second of wall time since this training started (learning included)."""
        elapsed = time.perf_counter() - self._start_time
        return (self.num_timesteps - self._start_steps) / elapsed if elapsed > 0 else 0.0

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            if done:
                self.episodes += 1
                self.endings[ending_of(info)] += 1
                if "episode" in info:  # the VecMonitor's statistics of the episode that just ended
                    self.recent_returns.append(float(info["episode"]["r"]))
        self.progress.update(self.snapshot())
        now = time.perf_counter()
        if now - self._last_log >= self.log_interval_s:
            self._last_log = now
            self.log_line()
        return True

    def _on_rollout_end(self) -> None:
        for ending, count in self.endings.items():
            self.logger.record(f"episodes/{ending}", count)
        self.logger.record("time/env_steps_per_s", self.steps_per_s)

    def _on_training_end(self) -> None:
        self.log_line()
        self.progress.update(self.snapshot(), finished=True)

    def snapshot(self) -> dict[str, Any]:
        mean = float(np.mean(self.recent_returns)) if self.recent_returns else None
        return {
            "num_timesteps": int(self.num_timesteps),
            "total_timesteps": int(self.total_timesteps),
            "episodes": self.episodes,
            "endings": dict(self.endings),
            "env_steps_per_s": round(self.steps_per_s, 2),
            "mean_recent_return": mean,
            "elapsed_s": round(time.perf_counter() - self._start_time, 2),
        }

    def log_line(self) -> None:
        snap = self.snapshot()
        log.info(
            "%d/%d steps, %d episodes, %.1f env-steps/s, endings %s, mean return (last %d) %s",
            snap["num_timesteps"],
            snap["total_timesteps"],
            snap["episodes"],
            snap["env_steps_per_s"],
            snap["endings"],
            len(self.recent_returns),
            "n/a" if snap["mean_recent_return"] is None else f"{snap['mean_recent_return']:.1f}",
        )


# --- checkpoints, progress bar, stop -----------------------------------------------------------------


class CheckpointCallback(sb3_callbacks.CheckpointCallback):
    """SB3's checkpoints (``<prefix>_<steps>_steps.zip``), keeping only the newest replay buffer on disk.

    ``every`` counts env steps whatever the number of envs (SB3's ``save_freq`` counts vector steps).
    """

    def __init__(self, every: int, save_path: str | Path, n_envs: int, save_replay_buffer: bool = True) -> None:
        super().__init__(
            save_freq=max(1, every // n_envs),
            save_path=str(save_path),
            name_prefix="model",
            save_replay_buffer=save_replay_buffer,
        )

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq != 0:
            return True
        older = set(Path(self.save_path).glob(f"{self.name_prefix}_replay_buffer_*_steps.pkl"))
        result = super()._on_step()
        log.info("checkpoint at %d steps in %s", self.num_timesteps, self.save_path)
        for path in older:
            path.unlink(missing_ok=True)
        return result


class WallClockLimit(BaseCallback):
    """Ends training at the next step once ``limit_s`` seconds have passed since ``started`` (a wall-time budget);
    the run is saved as after any other end."""

    def __init__(self, limit_s: float, started: float) -> None:
        super().__init__()
        self.limit_s = limit_s
        self.started = started

    def _on_step(self) -> bool:
        if time.perf_counter() - self.started < self.limit_s:
            return True
        log.info("wall-time budget of %g min spent: ending training at %d steps", self.limit_s / 60, self.num_timesteps)
        return False


class StopOnEvent(BaseCallback):
    """Ends training at the next step once ``event`` is set (by a SIGTERM/SIGINT handler), so the run is saved."""

    def __init__(self, event: threading.Event) -> None:
        super().__init__()
        self.event = event

    def _on_step(self) -> bool:
        if self.event.is_set():
            log.info("stop requested: ending training at %d steps", self.num_timesteps)
            return False
        return True
