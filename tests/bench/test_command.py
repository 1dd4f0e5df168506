"""`swimm bench --repeat N`: how several runs' results become one."""

from __future__ import annotations

import json

import pytest

from bench.command import BenchSettings, check, medians
from services.settings import SETTINGS_EXIT_CODE
from swimm.cli import main


def test_repeated_runs_report_each_numbers_median_and_a_flag_only_when_every_run_raised_it() -> None:
    fixed = {"steps": 2000, "transport": "low-latency"}
    runs = [
        {"ratio": 0.48, "p50_ms": 0.70, "same_episodes": True, "cpu": {"sim": 1.0}, **fixed},
        {"ratio": 0.56, "p50_ms": 0.60, "same_episodes": False, "cpu": {"sim": 2.0}, **fixed},
        {"ratio": 0.51, "p50_ms": 0.65, "same_episodes": True, "cpu": {"sim": 3.0}, **fixed},
    ]
    merged = medians(runs)
    assert merged["ratio"] == 0.51 and merged["p50_ms"] == 0.65
    assert merged["steps"] == 2000 and isinstance(merged["steps"], int)  # the same in every run: kept as it is
    assert merged["same_episodes"] is False  # one run played other episodes
    assert merged["transport"] == "low-latency" and merged["cpu"] == {"sim": 1.0}  # not numbers: the first run's


def test_repeat_below_one_is_refused_before_anything_runs() -> None:
    with pytest.raises(ValueError, match="--repeat 0: must be >= 1"):
        check(BenchSettings(target="sim", repeat=0))


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (BenchSettings(target="sim", profile="sim.prof"), "--profile is for one run of `swimm bench train`"),
        (BenchSettings(target="train", profile="x.prof", repeat=2), "without --repeat"),
        (BenchSettings(target="train", profile="/no/such/folder/x.prof"), "no folder /no/such/folder"),
    ],
)
def test_a_profile_the_run_could_not_write_is_refused_before_anything_runs(settings, message) -> None:
    with pytest.raises(ValueError, match=message):
        check(settings)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (BenchSettings(target="train", envs=8, encoders=0), "--encoders 0: must be >= 1"),
        (BenchSettings(target="train", envs=8, zenoh_threads=-1), "--zenoh-threads -1: must be >= 0"),
    ],
)
def test_a_layout_that_cannot_run_is_refused_before_anything_runs(settings, message) -> None:
    with pytest.raises(ValueError, match=message):
        check(settings)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "train", "--algo", "nonesuch"], "unknown algorithm 'nonesuch'"),
        (["bench", "train", "--algo", "no_such_module:Class"], "cannot import module 'no_such_module'"),
        (["bench", "nonesuch"], "unknown benchmark 'nonesuch'"),
    ],
)
def test_the_command_refuses_its_settings_before_measuring(argv, message, capsys) -> None:
    assert main(argv) == SETTINGS_EXIT_CODE
    assert f"bench refused its settings: {message}" in capsys.readouterr().err


def test_a_choice_outside_its_list_is_refused_by_the_parser(capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(["bench", "train", "--engine", "X"])
    assert stopped.value.code == 2 and "--engine: invalid choice: 'X'" in capsys.readouterr().err


def test_a_ceiling_asked_of_another_benchmark_is_refused_before_anything_runs() -> None:
    with pytest.raises(ValueError, match="--ceiling is for `swimm bench train`"):
        check(BenchSettings(target="sim", ceiling=True))


def test_a_json_report_says_what_made_it(capsys) -> None:
    """Committed benchmark JSON carries its provenance: the command, the commit, the host and its speed (the
    in-process World steps/s measured in the same run, beside which every speed figure is read)."""
    from bench.command import report
    from services.results import PROVENANCE_KEY

    assert report({"ratio": 0.5}, as_json=True) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["ratio"] == 0.5
    assert printed[PROVENANCE_KEY]["host"]["cores"] >= 1 and len(printed[PROVENANCE_KEY]["git"]["commit"]) == 40
    assert 50 < printed[PROVENANCE_KEY]["host_world_steps_per_s"] < 50_000  # a real World stepped, 64x64 frames


def test_a_json_report_extends_the_results_own_provenance(tmp_path, capsys) -> None:
    """A result that carries its provenance (bench learn's, as its summary file has it) keeps its models and seeds
    and gains the host's World steps/s; one that already has the figure is not measured again."""
    from bench.command import report
    from services.results import PROVENANCE_KEY, provenance

    encoder = tmp_path / "cmvae.pt"
    encoder.write_bytes(b"weights")
    about = provenance({"encoder": encoder}, seeds=[107, 109])
    assert report({PROVENANCE_KEY: about, "algos": {}}, as_json=True) == 0
    printed = json.loads(capsys.readouterr().out)
    assert list(printed) == [PROVENANCE_KEY, "algos"]
    assert printed[PROVENANCE_KEY]["models"] == about["models"] and printed[PROVENANCE_KEY]["seeds"] == [107, 109]
    assert printed[PROVENANCE_KEY]["written_utc"] == about["written_utc"]  # the result's own, not one made now
    assert 50 < printed[PROVENANCE_KEY]["host_world_steps_per_s"] < 50_000

    assert report({PROVENANCE_KEY: about | {"host_world_steps_per_s": 1234.5}, "ratio": 0.5}, as_json=True) == 0
    assert json.loads(capsys.readouterr().out)[PROVENANCE_KEY]["host_world_steps_per_s"] == 1234.5
    assert report({PROVENANCE_KEY: about, "ratio": 0.5}, as_json=False) == 0
    assert capsys.readouterr().out == "ratio  0.5\n"  # the table leaves the provenance to --json


def test_the_hosts_yardstick_is_measured_in_a_process_configured_as_swimms(monkeypatch) -> None:
    """A caller started with Mesa's threads set otherwise still gets a World stepped the way swimm's processes step
    it; a step count below one is refused by name."""
    import subprocess
    import sys

    from bench.host import host_world_steps_per_s

    monkeypatch.setenv("LP_NUM_THREADS", "2")
    assert 50 < host_world_steps_per_s(300) < 50_000
    done = subprocess.run([sys.executable, "-m", "bench.host", "0"], capture_output=True, text=True)
    assert done.returncode != 0 and "steps must be at least 1" in done.stderr


def test_a_yardstick_that_cannot_be_measured_loses_no_result(monkeypatch, capsys) -> None:
    """A World that cannot render in the yardstick's process (no such GL backend) leaves the figure out, not the
    benchmark's result."""
    from bench.command import report
    from services.results import PROVENANCE_KEY

    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")
    assert report({"ratio": 0.5}, as_json=True) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["ratio"] == 0.5 and printed[PROVENANCE_KEY]["host_world_steps_per_s"] is None
