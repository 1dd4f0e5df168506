"""`swimm bench learn --merge`: one results folder from the summaries of several benchmark runs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pandas as pd
import pytest

from bench.command import BenchSettings, run
from bench.learn_settings import LearnBenchSettings
from bench.scores import iqm
from services.results import PROVENANCE_KEY, provenance


def write_source(
    folder, name, algos: dict[str, list[float]], actor_average: int, seeds=(97, 101), about: dict | None = None
) -> str:
    """A summary with ``algos``' final returns (and the provenance ``about``) and an evaluations table of two
    evaluations per seed."""
    folder.mkdir(parents=True, exist_ok=True)
    summary = {"algos": {algo: {"seeds": list(seeds[: len(finals)]), "final_returns": finals,
                                "minutes_to": {"2000": [1.0] * len(finals)}}
                         for algo, finals in algos.items()},
               "settings": {"actor_average": actor_average, "seeds": list(seeds), "out": f"runs/{name}"},
               "how": "final_returns: 20 episodes"}  # fmt: skip
    if about:
        summary[PROVENANCE_KEY] = about
    (folder / f"{name}.json").write_text(json.dumps(summary))
    rows = [{"algo": algo, "seed": seed, "num_timesteps": steps, "wall_min": steps / 1000, "mean_return": final}
            for algo, finals in algos.items() for seed, final in zip(seeds, finals, strict=False)
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
    assert summary["algos"]["td3"]["settings"]["actor_average"] == 0 and summary["algos"]["td3"]["sources"] == [others]
    evaluations = pd.read_csv(out / "evaluations.csv")
    assert sorted(evaluations.groupby("algo").size().items()) == [("ppo", 2), ("sac", 4), ("td3", 2)]
    assert (out / "learn.png").read_bytes()[:4] == b"\x89PNG"


def test_one_recipes_seeds_from_two_summaries_are_pooled_and_aggregated_again(tmp_path) -> None:
    first = write_source(tmp_path, "first", {"sac": [2540.0, 2305.3, 2070.8]}, 500, seeds=(97, 101, 103))
    more = write_source(tmp_path, "more", {"sac": [2400.0, 1000.0]}, 500, seeds=(107, 109))
    later = json.loads(Path(more).read_text())  # ran after a setting was added: it records its default value
    later["settings"]["smooth"] = dataclasses.asdict(LearnBenchSettings().smooth)
    later["algos"]["sac"]["trained_steps"] = [150000, 120000]  # seed 109 ended by the wall-time budget
    Path(more).write_text(json.dumps(later))
    out = tmp_path / "merged"
    assert run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=["sac"], merge=[first, more],
                                                                      out=str(out)))) == 0  # fmt: skip
    sac = json.loads((out / "summary.json").read_text())["algos"]["sac"]
    assert sac["seeds"] == [97, 101, 103, 107, 109] and sac["sources"] == [first, more]
    assert sac["final_returns"] == [2540.0, 2305.3, 2070.8, 2400.0, 1000.0]
    assert (
        sac["final_iqm"] == round(float(iqm(sac["final_returns"])), 1) != round(float(iqm([2540.0, 2305.3, 2070.8])), 1)
    )
    assert sac["seeds_reaching"] == {"2000": 4, "2400": 2} and sac["minutes_to"] == {"2000": [1.0] * 5}
    assert sac["final_episode_returns"] == [None] * 5  # the sources kept no episode returns: none invented
    assert sac["trained_steps"] == [None, None, None, 150000, 120000]
    assert sac["settings"]["seeds"] == [97, 101, 103, 107, 109]
    evaluations = pd.read_csv(out / "evaluations.csv")
    assert sorted(evaluations["seed"].unique()) == [97, 101, 103, 107, 109]


def test_the_merges_provenance_names_the_pooled_seeds_and_the_encoder_every_source_ran(tmp_path, capsys) -> None:
    """The seeds of every merged algorithm, first seen first, and the encoder where every source's provenance names
    the same one (the same file in two checkouts), none where one ran another; printed as the file has it."""
    encoder, copy, other = tmp_path / "a" / "cmvae.pt", tmp_path / "b" / "cmvae.pt", tmp_path / "c" / "cmvae.pt"
    for path, weights in ((encoder, b"weights"), (copy, b"weights"), (other, b"other weights")):
        path.parent.mkdir()
        path.write_bytes(weights)
    sac_seeds, td3_seeds = (97, 101, 103), (97, 107)
    sac = write_source(tmp_path, "sac", {"sac": [2540.0, 2305.3, 2070.8]}, 500, seeds=sac_seeds,
                       about=provenance({"encoder": encoder}, seeds=sac_seeds))  # fmt: skip
    td3 = write_source(tmp_path, "td3", {"td3": [1900.0, 2000.0]}, 0, seeds=td3_seeds,
                       about=provenance({"encoder": copy}, seeds=td3_seeds))  # fmt: skip
    ppo = write_source(tmp_path, "ppo", {"ppo": [2085.1]}, 0, about=provenance({"encoder": other}, seeds=(97,)))
    out = tmp_path / "merged"
    learn = LearnBenchSettings(algos=["sac", "td3"], merge=[sac, td3, ppo], out=str(out))
    assert run(BenchSettings(target="learn", json=True, learn=learn)) == 0

    about = json.loads((out / "summary.json").read_text())[PROVENANCE_KEY]
    assert about["seeds"] == [97, 101, 103, 107]
    assert about["models"] == json.loads(Path(sac).read_text())[PROVENANCE_KEY]["models"] != {}
    assert about["host_world_steps_per_s"] is None  # the merge trains nothing: its wall times are the sources'
    hosts = {Path(source["summary"]).name: source for source in about["source_hosts"]}
    assert hosts.keys() == {Path(sac).name, Path(td3).name}  # the ppo source holds no merged algorithm
    assert hosts[Path(sac).name]["host"] == json.loads(Path(sac).read_text())[PROVENANCE_KEY]["host"]
    assert json.loads(capsys.readouterr().out)[PROVENANCE_KEY] == about  # --json prints the file's provenance

    learn = LearnBenchSettings(algos=["sac", "ppo"], merge=[sac, td3, ppo], out=str(out))
    assert run(BenchSettings(target="learn", learn=learn)) == 0
    about = json.loads((out / "summary.json").read_text())[PROVENANCE_KEY]
    assert about["seeds"] == [97, 101, 103] and about["models"] == {}  # ppo's source ran another encoder


def test_a_different_recipe_a_seed_twice_or_an_algorithm_in_none_is_refused_by_name(tmp_path) -> None:
    first = write_source(tmp_path, "first", {"sac": [2000.0]}, actor_average=0)
    other = write_source(tmp_path, "other", {"sac": [2100.0]}, actor_average=500, seeds=(107,))
    again = write_source(tmp_path, "again", {"sac": [2100.0]}, actor_average=0)
    out = tmp_path / "merged"
    refusals = (
        (["sac"], [first, other], r"sac is in .*first.json and .*other.json, which ran different recipes "
                                  r"\(actor_average differ\)"),
        (["sac"], [first, again], r"sac has a seed in two summaries \(seeds \[97, 97\]\)"),
        (["sac", "td3"], [first], "td3 is in none of the summaries"),
    )  # fmt: skip
    for algos, merge, message in refusals:
        with pytest.raises(ValueError, match=message):
            run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=algos, merge=merge, out=str(out))))
    assert not out.exists()


def test_summaries_that_differ_only_in_a_wall_time_cap_no_run_reached_are_pooled(tmp_path) -> None:
    """A slower host's runs of one recipe under a larger cap pool with the first runs when every run trained its
    step budget (``trained_steps``, or in older summaries minutes under the cap); a cap that cut a run refuses."""

    def source(name: str, seeds: tuple[int, ...], cap: float, **entry) -> str:
        path = write_source(tmp_path, name, {"ppo": [2300.0] * len(seeds)}, 500, seeds=seeds)
        summary = json.loads(Path(path).read_text())
        summary["settings"] |= {"budget_steps": 400_000, "budget_min": cap}
        summary["algos"]["ppo"] |= entry
        Path(path).write_text(json.dumps(summary))
        return path

    fast = source("fast", (107, 109), 25.0, wall_min=[13.7, 11.9])  # an older summary: no trained_steps
    slow = source("slow", (97, 101), 40.0, trained_steps=[401_408, 401_408], wall_min=[29.0, 25.9])
    cut = source("cut", (103,), 40.0, trained_steps=[327_680], wall_min=[40.0])
    out = tmp_path / "merged"
    learn = LearnBenchSettings(algos=["ppo"], merge=[slow, fast], out=str(out))
    assert run(BenchSettings(target="learn", learn=learn)) == 0
    assert json.loads((out / "summary.json").read_text())["algos"]["ppo"]["seeds"] == [97, 101, 107, 109]
    for merge in ([cut, fast], [fast, cut]):
        with pytest.raises(ValueError, match=r"which ran different recipes \(budget_min differ\)"):
            run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=["ppo"], merge=merge, out=str(out / "x"))))


def test_a_summary_without_its_evaluations_is_named(tmp_path) -> None:
    source = write_source(tmp_path, "lonely", {"sac": [2000.0]}, actor_average=0)
    (tmp_path / "lonely-evaluations.csv").unlink()
    with pytest.raises(ValueError, match="no such file .*lonely-evaluations.csv"):
        run(BenchSettings(target="learn", learn=LearnBenchSettings(algos=["sac"], merge=[source], out=str(tmp_path))))
