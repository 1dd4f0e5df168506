"""A contender's return against another's on the same episodes (eval_service/paired.py)."""

from __future__ import annotations

import numpy as np
import pytest

from eval_service.paired import describe_ratio, return_ratio, return_ratios


def test_a_scaled_copy_is_its_scale_with_no_spread() -> None:
    baseline = [1500.0, 2000.0, 2500.0]
    ratio = return_ratio([0.9 * value for value in baseline], baseline)
    assert ratio == {"ratio": pytest.approx(0.9), "ci95": [pytest.approx(0.9), pytest.approx(0.9)], "episodes": 3}


def test_pairing_keeps_the_episodes_spread_out_of_the_interval() -> None:
    """Hard and easy episodes move both contenders: paired, the interval is that of the ratio alone, far narrower
    than the episodes' own spread would make it, and it holds the ratio of the means."""
    rng = np.random.default_rng(1)
    baseline = rng.uniform(1000.0, 3000.0, size=20)
    returns = baseline * rng.normal(0.9, 0.02, size=20)
    ratio = return_ratio(returns, baseline)
    low, high = ratio["ci95"]
    assert ratio["ratio"] == pytest.approx(returns.mean() / baseline.mean())
    assert low < ratio["ratio"] < high and high - low < 0.05
    shuffled = return_ratio(rng.permutation(returns), baseline)  # the same returns, unpaired
    assert shuffled["ci95"][1] - shuffled["ci95"][0] > 3 * (high - low)


def test_no_ratio_where_it_says_nothing_and_mismatched_episodes_are_refused() -> None:
    assert return_ratio([2000.0], [2100.0]) is None  # one episode
    assert return_ratio([100.0, 200.0], [-50.0, 20.0]) is None  # a baseline losing on average
    with pytest.raises(ValueError, match="one per episode each: 3 against 2"):
        return_ratio([1.0, 2.0, 3.0], [1.0, 2.0])


def test_every_contender_is_set_against_the_first() -> None:
    ratios = return_ratios({"scripted": [2000.0, 2200.0], "sac": [1800.0, 2090.0], "ppo": [1000.0, 1100.0]})
    assert list(ratios) == ["sac", "ppo"] and {r["of"] for r in ratios.values()} == {"scripted"}
    assert ratios["ppo"]["ratio"] == pytest.approx(0.5)
    assert return_ratios({"scripted": [2000.0, 2200.0]}) == {}
    assert describe_ratio("ppo", ratios["ppo"]) == (
        "ppo: 50.0% of scripted's return (95% paired bootstrap 50.0 to 50.0%), 2 episodes"
    )
