"""The run folder of one evaluation: per-step CSV, per-episode CSV, JSON summary and figures.

<out>/steps.csv       one row per step (evaluator.STEP_FIELDS), written as the steps happen
<out>/episodes.csv    one row per episode (metrics.SUMMARY_ROW_FIELDS + seed, steps)

A 3d task's run folder (``vertical``) adds the elevation columns to both CSVs (VERTICAL_STEP_FIELDS, E); a pod's
adds the identity columns (IDENTITY_STEP_FIELDS, services.identity.IDENTITY_ROW_FIELDS), seen in its rows.
<out>/summary.json    Table 12 per label, the paper's SAC beside it, and how the run was made
<out>/returns.png     return per episode, violations marked by cause (the paper's Figures 13-14)
<out>/metrics.png     metrics per label beside the paper's SAC (Figure 16)
<out>/trajectory-<label>.png  rover and dolphin from above in the chosen episode, one per label
<out>/depth-<label>.png       the 3d task's: depths and elevation in the chosen episode, one per label
<out>/identity-<label>.png    a pod's: the dolphin followed in the chosen episode, occluded steps shaded, per label
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path
from typing import Any

import pandas as pd

from eval_service import plots
from learner_service.evaluation import IDENTITY_STEP_FIELDS, STEP_FIELDS, VERTICAL_STEP_FIELDS
from learner_service.metrics import SUMMARY_ROW_FIELDS, VERTICAL_ROW_FIELDS
from services.identity import IDENTITY_ROW_FIELDS
from services.results import write_result

log = logging.getLogger(__name__)

#: The paper's best (SAC, 100 evaluation episodes; the SPEC's "Paper's best results").
PAPER_SAC = {"mean_return": 2.40e3, "A": 2.67e-2, "D": 2.35e-1, "A'": 0.0, "D'": 0.0, "C'": 0.0,
             "S_A": 1.86e-1, "S_D": 8.08e-2}  # fmt: skip
PAPER_LABEL = "paper SAC"
EPISODE_FIELDS = (*SUMMARY_ROW_FIELDS, "seed", "steps")


class RunFolder:
    """Writes one evaluation's files; the step CSV streams, everything else is written by :meth:`finish`."""

    def __init__(self, path: str | Path, vertical: bool = False) -> None:
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self._steps_file = (self.path / "steps.csv").open("w", newline="")
        self._step_fields = (*STEP_FIELDS, *VERTICAL_STEP_FIELDS) if vertical else STEP_FIELDS
        self._episode_fields = (*EPISODE_FIELDS, *VERTICAL_ROW_FIELDS) if vertical else EPISODE_FIELDS
        self._steps: csv.DictWriter | None = None  # its header waits for the first row: a pod's has more columns
        self.episodes: list[dict[str, Any]] = []

    def write_step(self, row: dict[str, Any]) -> None:
        if self._steps is None:
            self._steps = self._step_writer(pod="followed" in row)
        self._steps.writerow(row)

    def _step_writer(self, pod: bool) -> csv.DictWriter:
        """The step CSV's writer, its header written: a pod's run adds the identity columns."""
        if pod:
            self._step_fields = (*self._step_fields, *IDENTITY_STEP_FIELDS)
        writer = csv.DictWriter(self._steps_file, fieldnames=self._step_fields)
        writer.writeheader()
        return writer

    def add_episode(self, row: dict[str, Any]) -> None:
        self.episodes.append(row)
        self._steps_file.flush()  # a watcher (or a crash) sees whole episodes

    def finish(self, summaries: dict[str, dict[str, float]], record: dict[str, Any], about: dict[str, Any],
               trajectory_episode: int | None = 1) -> Path:  # fmt: skip
        """Close the step CSV, write episodes.csv, summary.json (``record`` with its provenance ``about``) and the
        figures (the trajectory of episode ``trajectory_episode``; None: no figures); returns summary.json's path."""
        if self._steps is None:  # no step at all: the header still says what the columns are
            self._steps = self._step_writer(pod=False)
        self._steps_file.close()
        pod = self.episodes and all("identity_share" in row for row in self.episodes)
        columns = (*self._episode_fields, *IDENTITY_ROW_FIELDS) if pod else self._episode_fields
        episodes = pd.DataFrame(self.episodes, columns=list(columns))
        episodes.to_csv(self.path / "episodes.csv", index=False)
        summary_path = write_result(self.path / "summary.json", {"labels": summaries, PAPER_LABEL: PAPER_SAC, **record},
                                    about)  # fmt: skip
        if trajectory_episode is not None and not episodes.empty:
            self._figures(episodes, summaries, trajectory_episode)
        log.info("evaluation written to %s", self.path)
        return summary_path

    def _figures(self, episodes: pd.DataFrame, summaries: dict[str, dict[str, float]], trajectory_episode: int) -> None:
        plots.plot_returns(episodes, self.path / "returns.png")
        plots.plot_metrics(summaries, self.path / "metrics.png", PAPER_SAC, PAPER_LABEL)
        steps = pd.read_csv(self.path / "steps.csv")
        episode = min(max(1, trajectory_episode), int(episodes["episode"].max()))
        for label in summaries:
            plots.plot_trajectory(steps, label, episode, self.path / f"trajectory-{_file_safe(label)}.png")
            if "elevation" in self._step_fields:
                plots.plot_depth(steps, label, episode, self.path / f"depth-{_file_safe(label)}.png")
            if "followed" in self._step_fields:
                plots.plot_identity(steps, label, episode, self.path / f"identity-{_file_safe(label)}.png")


def _file_safe(label: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)
