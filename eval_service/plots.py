"""PNG figures of evaluation and training runs: returns per episode, behaviour metrics, paths, learning curves.

Plotting only: the numbers come from the evaluator's per-step CSV, its per-episode summary rows and the
learner's monitor files (column names in notes/interfaces.md), as pandas DataFrames or files. Each
``*_figure`` builds a `matplotlib.figure.Figure` without pyplot (no global figure registry, no display,
PNGs rendered by Agg) so tests and notebooks can inspect it; each ``plot_*`` saves one and returns the path.
"""

from __future__ import annotations

import json
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

log = logging.getLogger(__name__)

PathLike = str | Path

# Why an episode went wrong: the summary's flag column, and one colour and marker per cause in every figure.
VIOLATION_FLAGS = {"distance": "distance_exceeded", "visibility": "left_view", "collision": "collided"}
CAUSE_STYLES = {"distance": ("tab:red", "x"), "visibility": ("tab:orange", "v"), "collision": ("black", "s")}
TIME_LIMIT = "time limit"  # monitor rows whose cause is empty: the episode ran to its last step
CAUSE_COLOURS = {**{cause: colour for cause, (colour, _) in CAUSE_STYLES.items()}, TIME_LIMIT: "tab:gray"}

# The paper's Table 12 metrics, in its order, with what each bar measures.
METRIC_MEANINGS = {
    "A": "mean azimuth error / alpha",
    "D": "mean |d - opt_d| / max_d",
    "A'": "fraction of episodes losing view",
    "D'": "fraction of episodes past max_d",
    "C'": "fraction of episodes with a collision",
    "S_D": "surge smoothness (mean)",
    "S_A": "yaw smoothness (mean)",
    "mean_return": "mean episode return",
}

EPISODE_COLUMNS = ("label", "episode", "return", *VIOLATION_FLAGS.values())
STEP_COLUMNS = ("label", "episode", "step", "rover_x", "rover_y", "rover_yaw", "target_x", "target_y")
MONITOR_COLUMNS = ("r", "l")


def plot_returns(episodes_df: pd.DataFrame, path: PathLike) -> Path:
    """Return per episode for each label, episodes with violations marked by cause (the paper's Figures 13-14)."""
    return _save(returns_figure(episodes_df), path)


def plot_metrics(
    summary: Mapping[str, Mapping[str, float]],
    path: PathLike,
    reference: Mapping[str, float] | None = None,
    reference_label: str = "reference",
) -> Path:
    """Grouped bars: one panel per behaviour metric, one bar per label, the reference (e.g. paper SAC) beside."""
    return _save(metrics_figure(summary, reference, reference_label), path)


def plot_trajectory(steps_df: pd.DataFrame, label: str, episode: int, path: PathLike, arrow_every: int = 100) -> Path:
    """Rover and dolphin paths of one episode seen from above, rover heading arrows every ``arrow_every`` steps."""
    return _save(trajectory_figure(steps_df, label, episode, arrow_every), path)


def plot_training(
    monitor: pd.DataFrame | PathLike | Sequence[PathLike],
    path: PathLike,
    window: int = 20,
    evaluations: pd.DataFrame | None = None,
) -> Path:
    """Learning curve (reward per episode against training steps) and how episodes ended along the run;
    ``evaluations`` (a run folder's evaluations.csv) adds the evaluation callback's mean returns."""
    return _save(training_figure(monitor, window, evaluations), path)


def returns_figure(episodes_df: pd.DataFrame) -> Figure:
    """One line per label (return against episode) and one marker series per violation cause."""
    _require(episodes_df, EPISODE_COLUMNS, "episode summary")
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
    _require(steps_df, STEP_COLUMNS, "per-step table")
    if arrow_every < 1:
        raise ValueError(f"arrow_every must be >= 1, got {arrow_every}")
    rows = steps_df[(steps_df["label"].astype(str) == str(label)) & (steps_df["episode"] == episode)]
    if rows.empty:
        raise ValueError(f"no steps for label {label!r}, episode {episode}")
    rows = rows.sort_values("step")
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


def training_figure(
    monitor: pd.DataFrame | PathLike | Sequence[PathLike], window: int = 20, evaluations: pd.DataFrame | None = None
) -> Figure:
    """Reward per episode with a rolling mean above (and each evaluation's mean and sd of its deterministic
    episodes, where given: training episodes are stochastic, so the two differ), stacked counts of how
    episodes ended below."""
    episodes = monitor.copy() if isinstance(monitor, pd.DataFrame) else read_monitor(monitor)
    _require(episodes, MONITOR_COLUMNS, "monitor table")
    if episodes.empty:
        raise ValueError("monitor table has no episodes")
    if "t" in episodes:
        episodes = episodes.sort_values("t", kind="stable")
    steps = episodes["l"].cumsum().to_numpy(dtype=float)
    rewards = episodes["r"].to_numpy(dtype=float)
    window = max(1, min(window, len(episodes)))
    fig = Figure(figsize=(9, 6.5))
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    top.scatter(steps, rewards, s=6, alpha=0.35, color="tab:blue", label="episode reward")
    top.plot(
        steps,
        pd.Series(rewards).rolling(window, min_periods=1).mean(),
        color="tab:red",
        linewidth=1.5,
        label=f"rolling mean ({window} episodes)",
    )
    if evaluations is not None and not evaluations.empty:
        _require(evaluations, ("num_timesteps", "mean_return", "std_return"), "evaluations table")
        x, y, sd = (evaluations[c].to_numpy(dtype=float) for c in ("num_timesteps", "mean_return", "std_return"))
        top.errorbar(x, y, yerr=sd, fmt="D", color="black", markersize=5, capsize=3, label="evaluation (mean, sd)")
    top.set_title(f"Training: reward per episode ({len(episodes)} episodes, {int(steps[-1])} steps)")
    top.set_ylabel("episode reward (sum of per-step rewards)")
    top.grid(alpha=0.3)
    top.legend(fontsize=8)
    _cause_bars(bottom, steps, _causes(episodes))
    bottom.set_xlabel("training steps (environment steps)")
    bottom.set_ylabel("episodes ending per bin")
    bottom.set_title("How episodes ended")
    bottom.legend(fontsize=8)
    fig.tight_layout()
    return fig


def read_monitor(paths: PathLike | Iterable[PathLike]) -> pd.DataFrame:
    """Episodes from one or more monitor CSV files: a '#' JSON header line, then r, l, t (and extras such as cause).

    ``t`` counts from each file's own ``t_start``; adding it puts episodes of parallel environments on one clock.
    """
    paths = [paths] if isinstance(paths, str | Path) else list(paths)
    if not paths:
        raise ValueError("no monitor files given")
    frames = []
    for path in map(Path, paths):
        with path.open() as handle:
            first_line = handle.readline()
        has_header = first_line.startswith("#")
        frame = pd.read_csv(path, skiprows=1 if has_header else 0)
        if has_header and "t" in frame:
            frame["t"] += float(json.loads(first_line[1:]).get("t_start", 0.0))
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


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


def _causes(episodes: pd.DataFrame) -> pd.Series:
    if "cause" not in episodes:
        log.info("monitor table has no 'cause' column; counting every episode as reaching the time limit")
        return pd.Series(TIME_LIMIT, index=episodes.index)
    causes = episodes["cause"].astype(object).fillna("").astype(str).str.strip()
    return causes.where(causes != "", TIME_LIMIT)


def _cause_bars(ax: Axes, steps: np.ndarray, causes: pd.Series, max_bins: int = 20) -> None:
    """Counts of each ending per equal-width bin of training steps, stacked."""
    bins = min(max_bins, len(steps))
    edges = np.linspace(0.0, steps[-1], bins + 1)
    order = [c for c in CAUSE_COLOURS if c in set(causes)] + sorted(set(causes) - set(CAUSE_COLOURS))
    fallback = iter(["tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"] * len(order))
    below = np.zeros(bins)
    for cause in order:
        counts, _ = np.histogram(steps[(causes == cause).to_numpy()], bins=edges)
        ax.bar(
            edges[:-1],
            counts,
            width=np.diff(edges),
            bottom=below,
            align="edge",
            edgecolor="white",
            linewidth=0.4,
            color=CAUSE_COLOURS.get(cause) or next(fallback),
            label=cause,
        )
        below += counts


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


def _require(df: pd.DataFrame, columns: Sequence[str], what: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what} lacks columns {missing}")


def _save(fig: Figure, path: PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    log.info("wrote %s", path)
    return path
