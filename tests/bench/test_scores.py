"""The statistics of `swimm bench learn` on numbers worked out by hand: IQM, bootstrap intervals, time to a
return, learning-curve bands, and the summary's shape."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bench.learn import learning_figure, summarise
from bench.learn_settings import LearnBenchSettings
from bench.scores import bootstrap_ci, curve_band, first_reaching, iqm


def test_iqm_is_the_mean_of_the_middle_half() -> None:
    assert iqm([8, 1, 7, 2, 6, 3, 5, 4]) == pytest.approx(4.5)  # (3 + 4 + 5 + 6) / 4
    assert iqm([1, 2, 3, 4, 5, 6, 7, 1000]) == pytest.approx(4.5)  # one wild seed moves it not at all
    assert iqm([100.0, 200.0, 600.0]) == pytest.approx(300.0)  # under four runs nothing is cut: the mean


def test_bootstrap_interval_brackets_the_statistic_and_repeats() -> None:
    scores = [1800.0, 2100.0, 2200.0, 2300.0, 2450.0]
    low, high = bootstrap_ci(scores)
    assert min(scores) <= low <= iqm(scores) <= high <= max(scores)
    assert bootstrap_ci(scores) == (low, high)  # its own seeded generator
    wider_low, wider_high = bootstrap_ci([0.0, 2100.0, 2200.0, 2300.0, 4000.0])
    assert wider_high - wider_low > high - low
    assert bootstrap_ci([2000.0]) is None
    assert bootstrap_ci([2000.0, 2000.0]) == (2000.0, 2000.0)


def runs() -> list[pd.DataFrame]:
    first = pd.DataFrame({"num_timesteps": [10, 20, 30], "mean_return": [500.0, 2100.0, 2500.0]})
    second = pd.DataFrame({"num_timesteps": [15, 25], "mean_return": [1000.0, 1500.0]})
    return [first, second]


def test_first_reaching_reads_the_first_evaluation_at_or_above() -> None:
    first, second = runs()
    assert first_reaching(first, 2100.0, "num_timesteps") == 20.0
    assert first_reaching(first, 2400.0, "num_timesteps") == 30.0
    assert first_reaching(second, 2000.0, "num_timesteps") is None


def test_curve_band_holds_each_runs_latest_evaluation() -> None:
    band = curve_band(runs(), "num_timesteps", np.array([5.0, 10.0, 16.0, 22.0, 28.0, 30.0]))
    by_x = band.set_index("num_timesteps")
    assert 5.0 not in by_x.index  # no run had evaluated yet
    assert by_x.loc[10.0, "mean"] == 500.0 and by_x.loc[10.0, "runs"] == 1
    assert by_x.loc[16.0, "mean"] == pytest.approx(750.0) and by_x.loc[16.0, "runs"] == 2  # (500 + 1000) / 2
    assert by_x.loc[22.0, "mean"] == pytest.approx(1550.0)  # (2100 + 1000) / 2
    assert by_x.loc[30.0, "runs"] == 1 and by_x.loc[30.0, "mean"] == 2500.0  # the second run ended at 25
    assert (band["low"] <= band["mean"]).all() and (band["mean"] <= band["high"]).all()
    assert by_x.loc[22.0, "low"] >= 1000.0 and by_x.loc[22.0, "high"] <= 2100.0


def test_summary_has_the_documented_shape(tmp_path) -> None:
    settings = LearnBenchSettings(algos=["sac"], seeds=[97, 101], out=str(tmp_path))
    # seed 97's training ran 32 steps (its result.json); seed 101's left no result to read
    (tmp_path / "runs" / "sac-97").mkdir(parents=True)
    (tmp_path / "runs" / "sac-97" / "result.json").write_text('{"num_timesteps": 32, "stopped_early": false}')
    first, second = runs()
    evaluations = pd.concat(
        [
            run.assign(algo="sac", seed=seed, wall_min=run["num_timesteps"] / 10.0)
            for run, seed in ((first, 97), (second, 101))
        ]
    )
    finals = {("sac", 97): {"mean_return": 2450.0, "returns": [2400.0, 2500.0], "metrics": {"S_D": 0.1}},
              ("sac", 101): {"mean_return": 1400.0, "returns": [1300.0, 1500.0], "metrics": {"S_D": 0.2}}}  # fmt: skip
    bests = {("sac", 97): {"mean_return": 2480.0, "metrics": {}}}  # seed 101's best model not evaluated
    sac = summarise(settings, evaluations, finals, bests=bests)["algos"]["sac"]
    assert sac["best_model_returns"] == [2480.0, None]
    assert sac["seeds"] == [97, 101] and sac["final_returns"] == [2450.0, 1400.0]
    assert sac["final_iqm"] == pytest.approx(1925.0)
    assert sac["final_episode_returns"] == [[2400.0, 2500.0], [1300.0, 1500.0]]
    assert sac["seeds_reaching"] == {"2000": 1, "2400": 1}
    assert sac["minutes_to"] == {"2000": [2.0, None], "2400": [3.0, None]}
    assert sac["steps_to"]["2000"] == [20.0, None]
    assert sac["best_eval_returns"] == [2500.0, 1500.0] and sac["steps"] == [30, 25]
    assert sac["trained_steps"] == [32, None]
    assert learning_figure(evaluations).axes[1].get_xlabel() == "wall minutes"


def test_bad_bench_settings_are_named() -> None:
    with pytest.raises(ValueError, match="at least one algorithm"):
        LearnBenchSettings(algos=[]).check()
    with pytest.raises(ValueError, match="must not repeat"):
        LearnBenchSettings(seeds=[97, 97]).check()
    with pytest.raises(ValueError, match="budget-min"):
        LearnBenchSettings(budget_min=0).check()
    with pytest.raises(ValueError, match="final_episodes must be >= 1"):
        LearnBenchSettings(final_episodes=0).check()
