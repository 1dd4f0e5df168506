"""Aggregate learning results across seeds the way deep-RL research now reports them.

Following Agarwal et al. (NeurIPS 2021, the rliable library): a run's score is its final deterministic evaluation
(the mean return of its episodes); an algorithm's aggregate is the interquartile mean (IQM) of its runs' scores,
the mean of the middle half, robust to one lucky or failed seed yet using more than the median; its uncertainty
is a 95% percentile-bootstrap interval over runs (with one task, the stratified bootstrap is a bootstrap over
runs). With fewer than four runs no run falls outside the middle half, so the IQM equals the mean.
Learning curves are the mean across seeds with a bootstrap band of the same kind at each point.
Statistics come from scipy (`scipy.stats.trim_mean`, `scipy.stats.bootstrap`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats

CONFIDENCE = 0.95
RESAMPLES = 2000
SEED = 0  # the bootstrap's own generator: the same results give the same intervals


def iqm(scores: Sequence[float] | np.ndarray, axis: int = -1) -> float | np.ndarray:
    """Interquartile mean: the mean of the scores left after cutting a quarter off each end."""
    return stats.trim_mean(np.asarray(scores, dtype=float), 0.25, axis=axis)


def bootstrap_ci(scores: Sequence[float], statistic=iqm) -> tuple[float, float] | None:
    """95% percentile-bootstrap interval of ``statistic`` over the runs; None with fewer than two runs."""
    values = np.asarray(scores, dtype=float)
    if len(values) < 2:
        return None
    if np.all(values == values[0]):  # every resample gives the same value; scipy would warn and return NaN
        return float(values[0]), float(values[0])
    result = stats.bootstrap(
        (values,),
        statistic,
        vectorized=True,
        n_resamples=RESAMPLES,
        confidence_level=CONFIDENCE,
        method="percentile",
        rng=np.random.default_rng(SEED),
    )
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def final_aggregates(finals: Sequence[float], thresholds: Sequence[float]) -> dict:
    """An algorithm's aggregates over its seeds' final returns: IQM, its 95% interval, and how many seeds reach
    each threshold (the fields of a `swimm bench learn` summary)."""
    interval = bootstrap_ci(finals)
    return {
        "final_iqm": round(float(iqm(finals)), 1) if len(finals) else None,
        "final_iqm_ci95": [round(value, 1) for value in interval] if interval else None,
        "seeds_reaching": {f"{t:g}": sum(value >= t for value in finals) for t in thresholds},
    }


def first_reaching(evaluations: pd.DataFrame, threshold: float, column: str) -> float | None:
    """``column`` (e.g. wall minutes or steps) at the first evaluation whose mean return is at least ``threshold``."""
    reached = evaluations[evaluations["mean_return"] >= threshold]
    return None if reached.empty else float(reached[column].iloc[0])


def curve_band(runs: Sequence[pd.DataFrame], x: str, grid: np.ndarray) -> pd.DataFrame:
    """Mean return across runs at each ``grid`` value of ``x``, with a 95% bootstrap band.

    Each run holds its latest evaluation at or before the grid value (a step function, as a user would see it);
    before a run's first evaluation, or after it ended, it has no value there. Columns: x, mean, low, high, runs.
    """
    held = np.full((len(runs), len(grid)), np.nan)
    for row, evaluations in enumerate(runs):
        ordered = evaluations.sort_values(x)
        positions = np.searchsorted(ordered[x].to_numpy(), grid, side="right") - 1
        inside = (positions >= 0) & (grid <= ordered[x].iloc[-1])
        held[row, inside] = ordered["mean_return"].to_numpy()[positions[inside]]
    rows = []
    for column, value in enumerate(grid):
        present = held[~np.isnan(held[:, column]), column]
        if len(present) == 0:
            continue
        band = bootstrap_ci(present, statistic=np.mean) or (float(present[0]), float(present[0]))
        rows.append({x: float(value), "mean": float(present.mean()), "low": band[0], "high": band[1],
                     "runs": len(present)})  # fmt: skip
    return pd.DataFrame(rows, columns=[x, "mean", "low", "high", "runs"])
