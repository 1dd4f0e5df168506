"""PNG figures of evaluation runs: returns per episode, behaviour metrics, paths (training runs' learning curves:
learner_service.plots).

Plotting only: the numbers come from the evaluator's per-step CSV and its per-episode summary rows, as pandas
DataFrames or files. Each
``*_figure`` builds a `matplotlib.figure.Figure` without pyplot (no global figure registry, no display,
PNGs rendered by Agg) so tests and notebooks can inspect it; each ``plot_*`` saves one and returns the path.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from learner_service.plots import CAUSE_STYLES, PathLike, require_columns, save_figure
from services.geometry import BETA_DEG

log = logging.getLogger(__name__)

# Why an episode went wrong: the summary's flag column (colours and markers: learner_service.plots.CAUSE_STYLES).
VIOLATION_FLAGS = {"distance": "distance_exceeded", "visibility": "left_view", "collision": "collided"}

# The paper's Table 12 metrics, in its order, with what each bar measures.
METRIC_MEANINGS = {
    "A": "mean azimuth error / alpha",
    "D": "mean |d - opt_d| / max_d",
    "A'": "fraction of episodes losing view",
    "D'": "fraction of episodes past max_d",
    "C'": "fraction of episodes with a collision",
    "S_D": "surge smoothness (mean)",
    "S_A": "yaw smoothness (mean)",
    "E": "mean elevation error / beta (3d task)",
    "S_H": "heave smoothness (mean, 3d task)",
    "mean_return": "mean episode return",
}

EPISODE_COLUMNS = ("label", "episode", "return", *VIOLATION_FLAGS.values())
STEP_COLUMNS = ("label", "episode", "step", "rover_x", "rover_y", "rover_yaw", "target_x", "target_y")
DEPTH_COLUMNS = ("label", "episode", "step", "rover_z", "target_z", "elevation", "in_frustum")  # a 3d task's steps
IDENTITY_STEP_COLUMNS = ("label", "episode", "step", "followed", "target_occluded")  # a pod's steps


def plot_returns(episodes_df: pd.DataFrame, path: PathLike) -> Path:
    """Return per episode for each label, episodes with violations marked by cause (the paper's Figures 13-14)."""
    return save_figure(returns_figure(episodes_df), path)


def plot_metrics(
    summary: Mapping[str, Mapping[str, float]],
    path: PathLike,
    reference: Mapping[str, float] | None = None,
    reference_label: str = "reference",
) -> Path:
    """Grouped bars: one panel per behaviour metric, one bar per label, the reference (e.g. paper SAC) beside."""
    return save_figure(metrics_figure(summary, reference, reference_label), path)


def plot_trajectory(steps_df: pd.DataFrame, label: str, episode: int, path: PathLike, arrow_every: int = 100) -> Path:
    """Rover and dolphin paths of one episode seen from above, rover heading arrows every ``arrow_every`` steps."""
    return save_figure(trajectory_figure(steps_df, label, episode, arrow_every), path)


def plot_depth(steps_df: pd.DataFrame, label: str, episode: int, path: PathLike) -> Path:
    """The 3d task's vertical view of one episode: depths of rover and dolphin, and the elevation against beta."""
    return save_figure(depth_figure(steps_df, label, episode), path)


def plot_identity(steps_df: pd.DataFrame, label: str, episode: int, path: PathLike) -> Path:
    """A pod's episode: which dolphin the rover follows, the steps a companion hides the target shaded."""
    return save_figure(identity_figure(steps_df, label, episode), path)


def returns_figure(episodes_df: pd.DataFrame) -> Figure:
    """One line per label (return against episode) and one marker series per violation cause."""
    require_columns(episodes_df, EPISODE_COLUMNS, "episode summary")
    fig = Figure(figsize=(9, 4.5))
    ax = fig.add_subplot()
    for label, rows in _groups(episodes_df):
        ax.plot(rows["episode"], rows["return"], marker=".", linewidth=1, label=str(label))
    for cause, column in VIOLATION_FLAGS.items():
        violated = episodes_df[_flags(episodes_df[column])]
        if violated.empty:
            continue
        _mark_violations(ax, violated["episode"], violated["return"], cause, f"{len(violated)}", s=45, zorder=3)
    ax.set_title("Return per evaluation episode (markers: episodes with a violation)")
    ax.set_xlabel("episode")
    ax.set_ylabel("return (sum of per-step rewards in [-1, 1])")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def metrics_figure(
    summary: Mapping[str, Mapping[str, float]],
    reference: Mapping[str, float] | None = None,
    reference_label: str = "reference",
) -> Figure:
    """One panel per metric (their scales differ by 1e4); a missing value leaves its bar out."""
    if not summary:
        raise ValueError("metrics figure needs at least one label")
    reference = reference or {}
    labels = list(summary)
    colours = _label_colours(labels)
    metrics = [m for m in METRIC_MEANINGS if m in reference or any(m in values for values in summary.values())]
    if not metrics:
        raise ValueError(f"no known metric in the summary; expected some of {list(METRIC_MEANINGS)}")
    columns = min(4, len(metrics))
    rows = math.ceil(len(metrics) / columns)
    fig = Figure(figsize=(3.2 * columns, 3.3 * rows + 0.6))
    axes = fig.subplots(rows, columns, squeeze=False).ravel()
    for ax, metric in zip(axes, metrics, strict=False):
        bars = [(label, summary[label].get(metric), colours[label], "") for label in labels]
        bars.append((reference_label, reference.get(metric), "white", "//"))
        _metric_panel(ax, metric, [bar for bar in bars if bar[1] is not None])
    for ax in axes[len(metrics) :]:
        ax.set_visible(False)
    handles = [Patch(color=colours[label], label=label) for label in labels]
    if reference:
        handles.append(Patch(facecolor="white", edgecolor="black", hatch="//", label=reference_label))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 6), fontsize=8)
    fig.suptitle("Behaviour metrics (lower is better, except return)")
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig


def trajectory_figure(steps_df: pd.DataFrame, label: str, episode: int, arrow_every: int = 100) -> Figure:
    """Both paths in the horizontal plane (equal aspect, so turns and distances look as they were)."""
    require_columns(steps_df, STEP_COLUMNS, "per-step table")
    if arrow_every < 1:
        raise ValueError(f"arrow_every must be >= 1, got {arrow_every}")
    rows = _episode_rows(steps_df, label, episode)
    fig = Figure(figsize=(7, 7))
    ax = fig.add_subplot()
    ax.plot(rows["rover_x"], rows["rover_y"], color="tab:blue", linewidth=1.2, label="rover")
    ax.plot(rows["target_x"], rows["target_y"], color="tab:green", linewidth=1.2, label="dolphin")
    first, last = rows.iloc[0], rows.iloc[-1]
    ends = (("start", first, {"marker": "o", "s": 60, "facecolor": "none", "edgecolor": "black"}),
            ("end", last, {"marker": "s", "s": 50, "color": "black"}))  # fmt: skip
    for name, row, style in ends:
        ax.scatter([row["rover_x"], row["target_x"]], [row["rover_y"], row["target_y"]], zorder=3, label=name, **style)
    arrows = rows.iloc[::arrow_every]
    yaw = np.radians(arrows["rover_yaw"].to_numpy(dtype=float))
    ax.quiver(
        arrows["rover_x"],
        arrows["rover_y"],
        np.cos(yaw),
        np.sin(yaw),
        color="tab:blue",
        angles="xy",
        scale_units="inches",
        scale=3.0,
        width=0.004,
        zorder=4,
        label=f"rover heading (every {arrow_every} steps)",
    )
    _mark_violating_steps(ax, rows)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{label}, episode {episode}: paths seen from above ({len(rows)} steps)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def depth_figure(steps_df: pd.DataFrame, label: str, episode: int) -> Figure:
    """Depths over the episode, and the elevation with the band the view spans (+-beta), out-of-view steps marked."""
    require_columns(steps_df, DEPTH_COLUMNS, "3d task's per-step table")
    rows = _episode_rows(steps_df, label, episode)
    fig = Figure(figsize=(8, 6))
    depth, elevation = fig.subplots(2, 1, sharex=True)
    depth.plot(rows["step"], rows["rover_z"], color="tab:blue", linewidth=1.2, label="rover")
    depth.plot(rows["step"], rows["target_z"], color="tab:green", linewidth=1.2, label="dolphin")
    depth.set_ylabel("z (m, 0 at the surface)")
    depth.set_title(f"{label}, episode {episode}: depth and elevation ({len(rows)} steps)")
    elevation.axhspan(-BETA_DEG, BETA_DEG, color="tab:green", alpha=0.1, label="in the view's height (+-beta)")
    elevation.plot(rows["step"], rows["elevation"], color="black", linewidth=1.0, label="dolphin's elevation")
    out = rows[~_flags(rows["in_frustum"])]
    if not out.empty:
        _mark_violations(elevation, out["step"], out["elevation"], "visibility", f"{len(out)} steps", s=10, alpha=0.6)
    elevation.set_ylabel("elevation (deg)")
    elevation.set_xlabel("step")
    for ax in (depth, elevation):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def identity_figure(steps_df: pd.DataFrame, label: str, episode: int) -> Figure:
    """The followed dolphin step by step (none, the target, companion 1 on), the target's occluded steps shaded."""
    require_columns(steps_df, IDENTITY_STEP_COLUMNS, "pod's per-step table")
    rows = _episode_rows(steps_df, label, episode)
    occluded = _flags(rows["target_occluded"])
    top = max(int(rows["followed"].max()), 1)
    fig = Figure(figsize=(8, 3.5))
    ax = fig.subplots()
    ax.fill_between(rows["step"], -1.5, top + 0.5, where=occluded.to_numpy(), step="mid", color="tab:gray", alpha=0.3,
                    label=f"target occluded ({int(occluded.sum())} steps)")  # fmt: skip
    ax.step(rows["step"], rows["followed"], where="mid", color="black", linewidth=1.0, label="followed")
    ax.set_yticks(range(-1, top + 1), ["none", "target", *(f"companion {i}" for i in range(1, top + 1))])
    ax.set_ylim(-1.5, top + 0.5)
    ax.set_xlabel("step")
    ax.set_title(f"{label}, episode {episode}: the dolphin nearest the image centre ({len(rows)} steps)")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    return fig


def _episode_rows(steps_df: pd.DataFrame, label: str, episode: int) -> pd.DataFrame:
    """One episode's steps of one label, in step order; refused naming both when there are none."""
    rows = steps_df[(steps_df["label"].astype(str) == str(label)) & (steps_df["episode"] == episode)]
    if rows.empty:
        raise ValueError(f"no steps for label {label!r}, episode {episode}")
    return rows.sort_values("step")


def _metric_panel(ax: Axes, metric: str, bars: list[tuple[str, float, str, str]]) -> None:
    names = [name for name, *_ in bars]
    values = [float(value) for _, value, _, _ in bars]
    drawn = ax.bar(range(len(bars)), values, color=[c for *_, c, _ in bars], edgecolor="black", linewidth=0.6)
    for patch, (*_, hatch) in zip(drawn, bars, strict=True):
        patch.set_hatch(hatch)
    ax.bar_label(drawn, labels=[f"{v:.2e}" for v in values], fontsize=7)
    ax.set_xticks(range(len(bars)), names, rotation=30, ha="right", fontsize=8)
    ax.set_title(metric, fontsize=10)
    ax.set_ylabel(METRIC_MEANINGS[metric], fontsize=8)
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.margins(y=0.15)
    if min(values) >= 0:  # rates and errors: keep the axis at zero, and give all-zero panels a visible scale
        ax.set_ylim(bottom=0.0, top=None if max(values) > 0 else 1.0)


def _mark_violating_steps(ax: Axes, rows: pd.DataFrame) -> None:
    """Dots on the rover's path where the target was out of view, too far or touching."""
    conditions = {
        "visibility": ("in_frustum", False),
        "distance": ("distance_exceeded", True),
        "collision": ("collided", True),
    }
    for cause, (column, bad_when) in conditions.items():
        if column not in rows:
            continue
        bad = rows[_flags(rows[column]) == bad_when]
        if not bad.empty:
            _mark_violations(ax, bad["rover_x"], bad["rover_y"], cause, f"{len(bad)} steps", s=10, alpha=0.6)


def _mark_violations(ax: Axes, x: pd.Series, y: pd.Series, cause: str, count: str, **style: Any) -> None:
    """Scatter the points where ``cause`` was violated in its colour and marker, counted in the legend."""
    colour, marker = CAUSE_STYLES[cause]
    ax.scatter(x, y, color=colour, marker=marker, label=f"{cause} violated ({count})", **style)


def _label_colours(labels: Sequence[str]) -> dict[str, str]:
    return {label: f"C{i % 10}" for i, label in enumerate(labels)}


def _groups(df: pd.DataFrame) -> Iterable[tuple[object, pd.DataFrame]]:
    """Rows per label in first-appearance order, each sorted by episode."""
    for label in df["label"].drop_duplicates():
        yield label, df[df["label"] == label].sort_values("episode")


def _flags(values: pd.Series) -> pd.Series:
    """Booleans from a column that may have come back from CSV as bools, 0/1 or 'True'/'False' text."""
    if values.dtype == bool:
        return values
    if pd.api.types.is_numeric_dtype(values):
        return values.fillna(0) != 0
    return values.astype(str).str.strip().str.lower().isin(("true", "1", "yes"))
