"""Each contender's return against the first contender's on the same episodes.

Contenders of one evaluation play the same episodes (the same seeds), so their returns pair up episode by episode.
The ratio of mean returns, with a percentile bootstrap that resamples the episodes (both contenders' returns of an
episode together), is how the project's targets compare a policy with a tracker ("90% of the ground-truth
tracker's return"). Statistics from scipy (`scipy.stats.bootstrap`, paired).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
RESAMPLES = 10_000
SEED = 0  # the bootstrap's own generator: the same returns give the same interval


def _ratio_of_means(returns: np.ndarray, baseline: np.ndarray, axis: int = -1) -> np.ndarray:
    return returns.mean(axis=axis) / baseline.mean(axis=axis)


def return_ratio(returns: Sequence[float], baseline: Sequence[float]) -> dict[str, Any] | None:
    """Mean of ``returns`` over mean of ``baseline`` (paired, episode by episode) and its 95% interval; None where a
    ratio says nothing: fewer than two episodes, or a baseline whose mean return is not positive."""
    values, reference = np.asarray(returns, dtype=float), np.asarray(baseline, dtype=float)
    if values.shape != reference.shape:
        raise ValueError(f"paired returns need one per episode each: {len(values)} against {len(reference)}")
    if len(values) < 2 or reference.mean() <= 0:
        return None
    ratio = float(_ratio_of_means(values, reference))
    if np.ptp(values / reference) == 0:  # every resample gives the ratio; scipy would warn and return NaN
        low, high = ratio, ratio
    else:
        interval = stats.bootstrap((values, reference), _ratio_of_means, paired=True, vectorized=True,
                                   n_resamples=RESAMPLES, confidence_level=CONFIDENCE, method="percentile",
                                   rng=np.random.default_rng(SEED)).confidence_interval  # fmt: skip
        low, high = float(interval.low), float(interval.high)
    return {"ratio": ratio, "ci95": [low, high], "episodes": len(values)}


def return_ratios(returns_by_label: Mapping[str, Sequence[float]]) -> dict[str, dict[str, Any]]:
    """Every contender after the first against the first (``of``), where a ratio says something."""
    labels = list(returns_by_label)
    if len(labels) < 2:
        return {}
    baseline = labels[0]
    ratios = {label: return_ratio(returns_by_label[label], returns_by_label[baseline]) for label in labels[1:]}
    return {label: {"of": baseline, **ratio} for label, ratio in ratios.items() if ratio is not None}


def describe_ratio(label: str, ratio: Mapping[str, Any]) -> str:
    """One line for the log: ``sac: 100.9% of scripted's return (95% paired bootstrap 98.6 to 103.2%), 20 episodes``."""
    low, high = ratio["ci95"]
    return (f"{label}: {100 * ratio['ratio']:.1f}% of {ratio['of']}'s return (95% paired bootstrap "
            f"{100 * low:.1f} to {100 * high:.1f}%), {ratio['episodes']} episodes")  # fmt: skip
