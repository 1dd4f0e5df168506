"""`swimm bench learn --merge`: one results folder from the summaries of several benchmark runs."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from bench.command import BenchSettings, run
from bench.learn_settings import LearnBenchSettings


def write_source(folder, name, algos: dict[str, list[float]], actor_average: int) -> str:
    """A summary with ``algos``' final returns and an evaluations table of two evaluations per seed."""
    folder.mkdir(parents=True, exist_ok=True)
    summary = {"algos": {algo: {"seeds": [97, 101][: len(finals)], "final_returns": finals}
                         for algo, finals in algos.items()},
               "settings": {"actor_average": actor_average}, "how": "final_returns: 20 episodes"}  # fmt: skip
    (folder / f"{name}.json").write_text(json.dumps(summary))
    rows = [{"algo": algo, "seed": seed, "num_timesteps": steps, "wall_min": steps / 1000, "mean_return": final}
            for algo, finals in algos.items() for seed, final in zip([97, 101], finals, strict=False)
            for steps in (1000, 2000)]  # fmt: skip
    pd.DataFrame(rows).to_csv(folder / f"{name}-evaluations.csv", index=False)
    return str(folder / f"{name}.json")


def test_each_algorithm_comes_from_its_own_summary_with_its_settings(tmp_path) -> None:
    sac = write_source(tmp_path / "docs", "sac-runs", {"sac": [2540.0, 2305.3]}, actor_average=500)
    others = write_source(tmp_path / "docs", "others", {"ppo": [2085.1], "td3": [1900.0]}, actor_average=0)
    out = tmp_path / "merged"
    settings = LearnBenchSettings(algos=["sac", "ppo", "td3"], merge=[sac, others], out=str(out))
    assert run(BenchSettings(target="learn", learn=settings)) == 0

    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["algos"]) == ["sac", "ppo", "td3"]
    assert summary["algos"]["sac"]["final_returns"] == [2540.0, 2305.3]
    assert summary["algos"]["sac"]["settings"]["actor_average"] == 500
    assert summary["algos"]["td3"]["settings"]["actor_average"] == 0 and summary["algos"]["td3"]["source"] == others
    evaluations = pd.read_csv(out / "evaluations.csv")
    assert sorted(evaluations.groupby("algo").size().items()) == [("ppo", 2), ("sac", 4), ("td3", 2)]
    assert (out / "learn.png").read_bytes()[:4] == b"\x89PNG"


def test_an_algorithm_in_two_summaries_or_in_none_is_refused_by_name(tmp_path) -> None:
    first = write_source(tmp_path, "first", {"sac": [2000.0]}, actor_average=0)
    second = write_source(tmp_path, "second", {"sac": [2100.0]}, actor_average=0)
    out = tmp_path / "merged"
    with pytest.raises(ValueError, match="sac must be in exactly one summary, found in .*first.json, .*second.json"):
        run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=["sac"], merge=[first, second], out=str(out))))
    with pytest.raises(ValueError, match="td3 must be in exactly one summary, found in none"):
        run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=["sac", "td3"], merge=[first], out=str(out))))
    assert not out.exists()


def test_a_summary_without_its_evaluations_is_named(tmp_path) -> None:
    source = write_source(tmp_path, "lonely", {"sac": [2000.0]}, actor_average=0)
    (tmp_path / "lonely-evaluations.csv").unlink()
    with pytest.raises(ValueError, match="no such file .*lonely-evaluations.csv"):
        run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=["sac"], merge=[source], out=str(tmp_path))))
