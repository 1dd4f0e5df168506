"""Behaviour metrics of evaluation episodes: the paper's Table 12 (A, D, A', D', C', S_D, S_A) and returns.

A pod (telemetry ``pod_size`` > 1) adds the identity metrics of services/identity.py: per episode the share of
unoccluded steps the rover follows the target, whether that keeps identity, switches, occlusions and the steps to
re-acquire the target after one; the summary the share of episodes that kept identity and the means of the rest.

The 3d task adds E, the mean elevation error normalised as A is (by beta, half the vertical field of view), and
S_H, the heave command's smoothness computed as S_D and S_A are; its D is measured on the 3d distance. Planar
episodes have neither, so their rows and summaries are the paper's.

An :class:`EpisodeMetrics` is fed one step at a time, so the evaluator can
write its per-step CSV (with per-step smoothness) and the per-episode summary
row from the same numbers; :func:`summarise` folds summary rows into the
table's values.

Choices the SPEC leaves open, made here:
- Actions are (surge, yaw): component 0 is surge (S_D), component 1 is yaw (S_A).
  The SPEC's worked example fixes this: only that assignment gives S_D = 0.175 and S_A = 0.0425.
  The 3d task's (surge, heave, yaw) keeps surge first and yaw last, with heave (S_H) between.
- Smoothness at step t uses up to 10 previous actions *of this episode*, unpadded, with the raw weights
  W_1..W_n (no renormalisation when n < 10): the first step of an episode has S = 0.
- A is capped at 1 per step (the SPEC says so); D is not capped, so a policy that drifts far away in a
  3000-step evaluation episode (no early termination) shows it fully instead of saturating at 1.
- Episode-level A, D, S_D, S_A are means over that episode's steps; the summary averages episodes, so every
  episode weighs the same (they all run 3000 steps in evaluation anyway).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from learner_service.task import NO_CAUSE, violation_cause
from services.geometry import ALPHA_DEG, BETA_DEG, MAX_D, OPT_D
from services.identity import IDENTITY_ROW_FIELDS, episode_identity
from services.telemetry import Telemetry

#: Smoothness weights, W[0] for the most recent previous action (the SPEC's W_1).
SMOOTHNESS_WEIGHTS = np.array([0.25, 0.20, 0.15, 0.10, 0.08, 0.06, 0.05, 0.04, 0.04, 0.03])
SURGE, HEAVE, YAW = 0, 1, -1  # action components; heave only in the 3d task's (surge, heave, yaw)

SUMMARY_ROW_FIELDS = (
    "label",
    "episode",
    "return",
    "A",
    "D",
    "left_view",
    "distance_exceeded",
    "collided",
    "S_D",
    "S_A",
    "first_cause",
)
#: What a 3d task's summary row adds to SUMMARY_ROW_FIELDS.
VERTICAL_ROW_FIELDS = ("E", "S_H")
#: What a pod's summary adds to Table 12: the share of episodes that kept identity, then per-episode means.
IDENTITY_COLUMNS = ("identity_kept", "identity_share", "switches", "reacquire_steps")


def smoothness(history: Sequence[Sequence[float]], action: Sequence[float]) -> np.ndarray:
    """Per-component smoothness S_k = 1/2 * sum_i |a_t[k] - a_{t-i}[k]| * W_i of ``action`` after ``history``.

    ``history`` lists previous actions oldest to newest; only its last 10 count.
    """
    current = np.asarray(action, dtype=np.float64)
    recent = list(history)[-len(SMOOTHNESS_WEIGHTS) :][::-1]  # newest first, matching W_1, W_2, ...
    if not recent:
        return np.zeros_like(current)
    previous = np.asarray(recent, dtype=np.float64)
    weights = SMOOTHNESS_WEIGHTS[: len(previous), None]
    return 0.5 * np.sum(np.abs(current - previous) * weights, axis=0)


def named_smoothness(values: np.ndarray) -> dict[str, float]:
    """Per-component smoothness by metric name: S_D and S_A, and S_H for an action with heave."""
    named = {"S_D": float(values[SURGE]), "S_A": float(values[YAW])}
    if len(values) == 3:
        named["S_H"] = float(values[HEAVE])
    return named


def pod_identity(telemetry: Telemetry) -> tuple[int, bool] | None:
    """A pod's step for the identity metrics (who is followed, whether the target is occluded); None alone."""
    return (telemetry.followed, telemetry.target_occluded) if telemetry.pod_size > 1 else None


def elevation_error(phi: float) -> float:
    """One step's term of E: the unsigned elevation error over beta, capped at 1 like A's."""
    return min(abs(phi), BETA_DEG) / BETA_DEG


class EpisodeMetrics:
    """Accumulates one episode's steps into its summary row."""

    def __init__(self, label: str = "", episode: int = 0) -> None:
        self.label = label
        self.episode = episode
        self.steps = 0
        self.total_reward = 0.0
        self.left_view = False
        self.distance_exceeded = False
        self.collided = False
        self.first_cause = NO_CAUSE
        self._angle_error_sum = 0.0
        self._distance_error_sum = 0.0
        self._elevation_error_sum: float | None = None  # stays None in planar episodes, which have no E
        self._smoothness_sum: np.ndarray | float = 0.0  # per action component once the first step is in
        self._history: deque[np.ndarray] = deque(maxlen=len(SMOOTHNESS_WEIGHTS))
        self._followed: list[int] = []  # a pod's steps only (a lone dolphin has no identity to keep)
        self._occluded: list[bool] = []

    def add(
        self,
        d: float,
        theta: float,
        in_frustum: bool,
        collided: bool,
        action: Sequence[float],
        reward: float,
        phi: float | None = None,
        identity: tuple[int, bool] | None = None,
    ) -> dict[str, float]:
        """Record one step (``theta`` unsigned, degrees; ``action`` the task's); returns its smoothness by name.

        ``phi`` is the 3d task's unsigned elevation error in degrees (None in the planar task); ``identity`` a pod's
        (followed dolphin, target occluded), from :func:`pod_identity` (None for a lone dolphin).
        """
        if identity is not None:
            self._followed.append(identity[0])
            self._occluded.append(identity[1])
        act = np.asarray(action, dtype=np.float64)
        step_smoothness = smoothness(self._history, act)
        self._history.append(act)
        self._smoothness_sum += step_smoothness
        self._angle_error_sum += min(abs(theta), ALPHA_DEG) / ALPHA_DEG
        self._distance_error_sum += abs(d - OPT_D) / MAX_D
        if phi is not None:
            self._elevation_error_sum = (self._elevation_error_sum or 0.0) + elevation_error(phi)
        self.total_reward += reward
        self.steps += 1
        self.left_view |= not in_frustum
        self.collided |= collided
        self.distance_exceeded |= abs(d - OPT_D) >= MAX_D
        if self.first_cause == NO_CAUSE:
            self.first_cause = violation_cause(d, in_frustum, collided)
        return named_smoothness(step_smoothness)

    def row(self) -> dict[str, Any]:
        """The per-episode summary row (interfaces.md field names)."""
        if self.steps == 0:
            raise ValueError(f"episode {self.episode} of {self.label!r} has no steps to summarise")
        smooth = named_smoothness(self._smoothness_sum / self.steps)
        row = {
            "label": self.label,
            "episode": self.episode,
            "return": self.total_reward,
            "A": self._angle_error_sum / self.steps,
            "D": self._distance_error_sum / self.steps,
            "left_view": self.left_view,
            "distance_exceeded": self.distance_exceeded,
            "collided": self.collided,
            "S_D": smooth["S_D"],
            "S_A": smooth["S_A"],
            "first_cause": self.first_cause,
        }
        if self._elevation_error_sum is not None:
            row["E"] = self._elevation_error_sum / self.steps
        if "S_H" in smooth:
            row["S_H"] = smooth["S_H"]
        if self._followed:
            row |= episode_identity(self._followed, self._occluded)
        return row


def summarise(episodes: Iterable[Mapping[str, Any] | EpisodeMetrics]) -> dict[str, float]:
    """Table 12 over episodes (summary rows or accumulators): means of A, D, S_D, S_A; fractions A', D', C'.

    Episodes of the 3d task add the means of E and S_H.

    ``std_return`` is the population standard deviation (ddof 0), like the paper's tables over 100 episodes.
    """
    rows = [e.row() if isinstance(e, EpisodeMetrics) else e for e in episodes]
    if not rows:
        raise ValueError("no episodes to summarise")

    def column(name: str) -> np.ndarray:
        return np.asarray([row[name] for row in rows], dtype=np.float64)

    returns = column("return")
    summary = {
        "episodes": float(len(rows)),
        "A": float(column("A").mean()),
        "D": float(column("D").mean()),
        "A'": float(column("left_view").mean()),
        "D'": float(column("distance_exceeded").mean()),
        "C'": float(column("collided").mean()),
        "S_D": float(column("S_D").mean()),
        "S_A": float(column("S_A").mean()),
        "mean_return": float(returns.mean()),
        "std_return": float(returns.std()),
    }
    for name in VERTICAL_ROW_FIELDS:
        if all(name in row for row in rows):
            summary[name] = float(column(name).mean())
    if all(name in row for row in rows for name in IDENTITY_ROW_FIELDS):
        summary |= _identity_summary(column)
    return summary


def _identity_summary(column) -> dict[str, float]:
    """A pod's identity columns over episodes; an episode's NaN (nothing to measure) is left out of its mean."""

    def mean(name: str) -> float:
        values = column(name)
        values = values[~np.isnan(values)]
        return float(values.mean()) if values.size else float("nan")

    return {name: mean(name) for name in IDENTITY_COLUMNS}
