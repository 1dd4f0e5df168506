"""The training summary figure (``summary.png`` of a run folder) and the monitor files it reads, plus the plotting
helpers the evaluation figures (eval_service.plots) share with it.

Each ``*_figure`` builds a `matplotlib.figure.Figure` without pyplot (no global figure registry, no display, PNGs
rendered by Agg), so tests can inspect it; each ``plot_*`` saves one and returns the path.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure

log = logging.getLogger(__name__)

PathLike = str | Path

# One colour and marker per way an episode can go wrong, in every figure.
CAUSE_STYLES = {"distance": ("tab:red", "x"), "visibility": ("tab:orange", "v"), "collision": ("black", "s")}
TIME_LIMIT = "time limit"  # monitor rows whose cause is empty: the episode ran to its last step
CAUSE_COLOURS = {**{cause: colour for cause, (colour, _) in CAUSE_STYLES.items()}, TIME_LIMIT: "tab:gray"}
MONITOR_COLUMNS = ("r", "l")


def plot_training(
    monitor: pd.DataFrame | PathLike | Sequence[PathLike],
    path: PathLike,
    window: int = 20,
    evaluations: pd.DataFrame | None = None,
) -> Path:
    """Learning curve (reward per episode against training steps) and how episodes ended along the run;
    ``evaluations`` (a run folder's evaluations.csv) adds the evaluation callback's mean returns."""
    return save_figure(training_figure(monitor, window, evaluations), path)


def training_figure(
    monitor: pd.DataFrame | PathLike | Sequence[PathLike], window: int = 20, evaluations: pd.DataFrame | None = None
) -> Figure:
    """Reward per episode with a rolling mean above (and each evaluation's mean and sd of its deterministic
    episodes, where given: training episodes are stochastic, so the two differ), stacked counts of how
    episodes ended below."""
    episodes = monitor.copy() if isinstance(monitor, pd.DataFrame) else read_monitor(monitor)
    require_columns(episodes, MONITOR_COLUMNS, "monitor table")
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
        require_columns(evaluations, ("num_timesteps", "mean_return", "std_return"), "evaluations table")
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


def require_columns(df: pd.DataFrame, columns: Sequence[str], what: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what} lacks columns {missing}")


def save_figure(fig: Figure, path: PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    log.info("wrote %s", path)
    return path
