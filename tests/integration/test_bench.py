"""`swimm bench sim | encoder | train --json` as a user runs them, on little work: one JSON object with the keys
the docs promise, rates that are rates, and (train) the distributed run reproducing the in-process one.

Benchmarks print what they measure and never pass or fail on speed; these tests check that they run and
measure what they say, not how fast anything is.
"""

from __future__ import annotations

import json
import math
import pstats
import shutil
import subprocess
import sys
import time

import pandas as pd
import pytest

from services.results import PROVENANCE_KEY

pytestmark = pytest.mark.slow


def bench(*args: str, timeout_s: float = 300.0) -> dict:
    result = subprocess.run(
        [sys.executable, "-m", "swimm", "bench", *args, "--json"], capture_output=True, text=True,
        timeout=timeout_s,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, result.stdout  # one JSON object, nothing else on stdout
    return json.loads(lines[0])


def assert_rates(result: dict, *keys: str) -> None:
    for key in keys:
        assert isinstance(result[key], float) and math.isfinite(result[key]) and result[key] > 0, (key, result)


def test_bench_sim_times_each_way_of_serving_against_the_in_process_steps_it_alternated_with() -> None:
    """Two runs (``--repeat 2``): each one's numbers, and their medians at the top."""
    result = bench("sim", "--steps", "200", "--repeat", "2")
    assert result["repeat"] == 2 and len(result["runs"]) == 2
    for run in result["runs"]:
        assert run["topology"] == "peer" and run["poll_ms"] > 0 and run["steps"] == 200 and run["rounds"] > 1
        assert run["transport"] == "low-latency"
        for prefix in ("", "standard_", "blocking_", "routed_"):
            rate, inprocess = f"{prefix or 'distributed_'}steps_per_s", f"{prefix}inprocess_steps_per_s"
            assert_rates(run, inprocess, rate, f"{prefix}p50_ms")
            assert run[f"{prefix}ratio"] == pytest.approx(run[rate] / run[inprocess], 1e-2)
            assert run[f"{prefix}p50_ms"] <= run[f"{prefix}p99_ms"]
    assert result["ratio"] == pytest.approx(sum(run["ratio"] for run in result["runs"]) / 2, abs=1e-3)


def test_bench_sim_with_several_envs_steps_them_in_groups_on_two_sims() -> None:
    result = bench("sim", "--steps", "200", "--envs", "4")
    assert (result["envs"], result["grouped_sims"], result["grouped_group_size"]) == (4, 2, 2)
    assert_rates(result, "grouped_inprocess_steps_per_s", "grouped_steps_per_s", "grouped_vector_step_p50_ms")
    assert result["grouped_ratio"] == pytest.approx(
        result["grouped_steps_per_s"] / result["grouped_inprocess_steps_per_s"], 1e-2
    )


@pytest.mark.parametrize(("transport", "zenoh_threads"), [("standard", 1), ("low-latency", 0)])
def test_bench_train_runs_the_same_episodes_in_process_and_through_the_services(
    transport: str, zenoh_threads: int
) -> None:
    """Either transport, and Zenoh on one thread (the default) or on its own pools, in every process."""
    flags = ("--low-latency",) if transport == "low-latency" else ()
    result = bench("train", "--algo", "sac", "--steps", "300", "--policy", "scratch", "--zenoh-threads",
                   str(zenoh_threads), *flags)  # fmt: skip
    assert_rates(result, "inprocess_steps_per_s", "distributed_steps_per_s")
    assert (result["algo"], result["topology"], result["transport"]) == ("sac", "peer", transport)
    assert result["zenoh_threads"] == zenoh_threads
    assert (result["start"], result["envs"], result["sims"], result["group_size"]) == ("scratch", 1, 1, 0)
    assert result["steps"] >= 300 and result["episodes"] >= 1
    assert result["same_episodes"] is True  # the ratio compares the same training, step for step
    assert set(result["distributed_cpu_ms_per_step"]) == {"learner", "router", "sim-0", "encoder"}


def test_bench_train_on_several_envs_splits_them_between_two_sims_in_groups(tmp_path) -> None:
    """From the shipped policy (the steady state's default), 4 envs: two sims, one group of 2 envs each; the
    learner's profile shows where its time went, down to the vector env's steps; the ceiling, two in-process
    loops at once, is set against the one in-process loop and the pipeline."""
    profile = tmp_path / "learner.prof"
    result = bench("train", "--algo", "sac", "--envs", "4", "--steps", "400", "--profile", str(profile), "--ceiling")
    calls = {name: stats[1] for (_, _, name), stats in pstats.Stats(str(profile)).stats.items()}
    assert calls["step_wait"] >= 400 // 4 and calls["learn"] == 1  # the distributed half's learn(), profiled whole
    assert result["start"].endswith("sac_cmvae.zip")
    assert (result["envs"], result["sims"], result["group_size"]) == (4, 2, 2)
    assert_rates(result, "distributed_rollout_steps_per_s", "rollout_ratio", "distributed_steps_per_s", "ratio")
    assert result["rollout_ratio"] == pytest.approx(
        result["distributed_rollout_steps_per_s"] / result["inprocess_rollout_steps_per_s"], 1e-2
    )
    assert set(result["distributed_cpu_ms_per_step"]) == {"learner", "router", "sim-0", "sim-1", "encoder"}
    assert_rates(result, "ceiling_rollout_steps_per_s", "ceiling_ratio", "share_of_ceiling")
    inprocess = result["inprocess_rollout_steps_per_s"]
    assert result["ceiling_ratio"] == pytest.approx(result["ceiling_rollout_steps_per_s"] / inprocess, 1e-2)
    assert result["share_of_ceiling"] == pytest.approx(result["rollout_ratio"] / result["ceiling_ratio"], 1e-2)
    assert "same_episodes" not in result  # four envs play other episodes than the one in-process env


def test_bench_encoder_compares_batch_one_with_many_envs() -> None:
    result = bench("encoder", "--steps", "100", "--envs", "4")
    assert_rates(result, "batch1_images_per_s", "batched_images_per_s")
    assert result["envs"] == 4
    assert result["ratio"] == pytest.approx(result["batched_images_per_s"] / result["batch1_images_per_s"], 1e-2)


def test_bench_learn_trains_seeds_over_real_processes_and_resumes(tmp_path) -> None:
    """Two tiny SAC runs through `swimm up` and their final evaluations; run again, nothing is trained twice."""
    out = tmp_path / "learn"
    args = ("learn", "--algos", "sac", "--seeds", "97", "101", "--budget-steps", "200", "--eval-every", "100",
            "--eval-episodes", "1", "--eval-max-steps", "40", "--final-episodes", "2", "--out", str(out))  # fmt: skip
    summary = bench(*args, timeout_s=600)
    sac = summary["algos"]["sac"]
    assert sac["seeds"] == [97, 101] and len(sac["final_returns"]) == 2
    for seed, final in zip(sac["seeds"], sac["final_returns"], strict=True):
        episodes = pd.read_csv(out / "runs" / f"sac-{seed}" / "final-eval" / "episodes.csv")
        assert len(episodes) == 2 and (episodes["steps"] == 40).all()
        assert final == pytest.approx(episodes["return"].mean(), abs=0.05)
    assert [len(returns) for returns in sac["final_episode_returns"]] == [2, 2]  # an interval over episodes later
    assert all(steps >= 200 for steps in sac["trained_steps"])  # the step budget, not the wall time, ended both
    for seed, best in zip(sac["seeds"], sac["best_model_returns"], strict=True):  # the best model, same episodes
        episodes = pd.read_csv(out / "runs" / f"sac-{seed}" / "best-eval" / "episodes.csv")
        assert len(episodes) == 2 and best == pytest.approx(episodes["return"].mean(), abs=0.05)
    assert set(sac["minutes_to"]) == {"2000", "2400"} and all(len(v) == 2 for v in sac["minutes_to"].values())
    evaluations = pd.read_csv(out / "evaluations.csv")
    assert set(evaluations["seed"]) == {97, 101} and (evaluations["num_timesteps"] >= 100).all()
    assert (evaluations["wall_min"] > 0).all()
    assert (out / "learn.png").read_bytes()[:4] == b"\x89PNG"
    written = json.loads((out / "summary.json").read_text())
    assert written["algos"] == summary["algos"]
    about = written[PROVENANCE_KEY]
    assert about["seeds"] == [97, 101] and about["models"]["encoder"]["sha256"] and about["git"]["commit"]

    started = time.monotonic()
    again = bench(*args, timeout_s=300)
    assert again["algos"] == summary["algos"]  # read back, not trained again
    assert time.monotonic() - started < 60

    # Trained but not evaluated (the evaluation was stopped): only the evaluations run again, to the same returns.
    run = out / "runs" / "sac-101"
    trained_at = (run / "final_model.zip").stat().st_mtime_ns
    shutil.rmtree(run / "final-eval")
    shutil.rmtree(run / "best-eval")
    evaluated = bench(*args, timeout_s=300)
    assert (run / "final_model.zip").stat().st_mtime_ns == trained_at
    assert evaluated["algos"]["sac"]["final_returns"] == summary["algos"]["sac"]["final_returns"]
