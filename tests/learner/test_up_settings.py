"""Settings refused by name before anything starts, and a child that refuses its settings never restarted."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from learner_service.learn_settings import LearnCommandSettings
from learner_service.up import LocalSystem, ServiceDied, UpSettings, child_commands
from services.procs import ProcessGroup
from services.settings import SETTINGS_EXIT_CODE, from_command_line
from sim_service.settings import SimSettings


def swimm(*argv: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "swimm", *argv], capture_output=True, text=True, timeout=60, cwd=cwd)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (("eval", "--episodes", "-1"), "eval refused its settings: --episodes -1: must be >= 1"),
        (("sim", "--train-envs", "-1"), "sim refused its settings: --train-envs -1: must be >= 0"),
        (("learn", "--steps", "-5"), "learn refused its settings: --steps -5: must be >= 0"),
        (("status", "--window-s", "0"), "status refused its settings: --window-s 0.0: must be > 0"),
        (("encoder", "--max-batch", "0"), "encoder refused its settings: --max-batch 0: must be >= 1"),
        (("router", "--zenoh-threads", "-1"), "router refused its settings: --zenoh-threads -1: must be >= 0"),
        (("dataset", "--count", "0"), "dataset refused its settings: --count 0: must be >= 1"),
    ],
)
def test_each_command_refuses_a_value_by_its_flag_and_range(argv, message) -> None:
    result = swimm(*argv)
    assert result.returncode == SETTINGS_EXIT_CODE, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr


def test_a_yaml_key_and_a_variable_are_named_as_written(tmp_path: Path) -> None:
    config = tmp_path / "learn.yaml"
    config.write_text("demo:\n  steps: -3\n")
    result = swimm("learn", "--config", str(config))
    assert result.returncode == SETTINGS_EXIT_CODE
    assert f"settings file {config}: setting 'demo_steps' got -3: must be >= 0" in result.stderr
    env = {**__import__("os").environ, "SWIMM_ENVS": "0"}
    result = subprocess.run([sys.executable, "-m", "swimm", "learn"], capture_output=True, text=True,
                            timeout=60, env=env)  # fmt: skip
    assert "environment variable SWIMM_ENVS: setting 'envs' got 0: must be >= 1" in result.stderr


def test_a_child_that_refuses_its_settings_is_not_restarted(tmp_path: Path) -> None:
    """A real sim process given a bad setting exits 2; the supervisor ends the run at once, no back-off."""
    with ProcessGroup(tmp_path / "logs") as group:
        sim = group.start("sim", "sim", "--train-envs", "-1")
        assert sim.process.wait(timeout=60) == SETTINGS_EXIT_CODE
        system = LocalSystem(UpSettings(restart_limit=3), group, tmp_path, threading.Event())
        with pytest.raises(ServiceDied, match="sim refused its settings \\(not restarted\\)"):
            system.check_services()
        assert sim.restarts == 0 and not system.restart_due
        with pytest.raises(RuntimeError, match="would refuse them again"):
            group.restart(sim)


def test_a_runs_end_names_every_file_it_saved_and_the_command_that_resumes_it(tmp_path: Path) -> None:
    """A real (tiny, in-process) run folder; the resume command's settings file loads back as this run's."""
    from learner_service.command import Training
    from learner_service.up import what_the_run_saved, write_up_config
    from tests.learner.test_command import tiny_settings

    run_dir = tmp_path / "run"
    Training(tiny_settings(run_dir)).run()
    settings = UpSettings(learn=tiny_settings(run_dir, backend="zenoh", steps=300), sims=1, port=0)
    write_up_config(settings, run_dir)
    text = what_the_run_saved(run_dir, settings.learn)
    for line in (
        f"saved in {run_dir}:",
        "final_model.zip (+ final_model_replay_buffer.pkl, its replay buffer): the model as training ended",
        "best_model.zip: the best evaluated policy, return",
        "checkpoints/model_200_steps.zip: the newest of 2 checkpoints",
        f"evaluate the policy: swimm eval --backend inprocess --algo sac --obs state --checkpoint {run_dir}/best_model",
        f"resume training: swimm up --config {run_dir}/up.yaml --resume {run_dir}/final_model.zip",
    ):
        assert line in text, text
    three_d = dataclasses.replace(settings.learn, task="3d")
    assert f"--checkpoint {run_dir}/best_model.zip --task 3d --episodes 20" in what_the_run_saved(run_dir, three_d)
    pod = dataclasses.replace(settings.learn, sim_config="sim_service/configs/pod4.yaml")
    assert "best_model.zip --sim-config sim_service/configs/pod4.yaml --episodes 20" in what_the_run_saved(run_dir, pod)
    resumed = from_command_line(
        UpSettings, ["--config", str(run_dir / "up.yaml"), "--resume", str(run_dir / "final_model.zip")]
    )
    assert resumed.learn.run_dir == str(run_dir) and resumed.learn.steps == 300 and resumed.port == 0
    assert (
        resumed.learn.resume == str(run_dir / "final_model.zip")
        and resumed.learn.hyperparams == settings.learn.hyperparams
    )


@pytest.mark.parametrize("task", ["planar", "3d"])
def test_the_sims_swim_the_dolphin_of_the_learners_task(task: str) -> None:
    settings = UpSettings(learn=LearnCommandSettings(obs="state", task=task, envs=4), sims=2)
    for _, command, arguments in child_commands(settings, "tcp/127.0.0.1:7447", None):
        assert command == "sim"
        assert from_command_line(SimSettings, arguments, environ={}).world.dolphin.motion == task


def test_an_encoder_file_that_is_no_cmvae_is_refused_by_the_encoder_check_before_any_service_starts(tmp_path) -> None:
    notes = tmp_path / "notes.pt"
    notes.write_text("not a model")
    result = swimm("up", "--encoder-checkpoint", str(notes), "--run-dir", str(tmp_path / "run"))
    assert result.returncode == SETTINGS_EXIT_CODE, result.stderr
    assert f"the encoder it would start refuses its settings: {notes} is not a swimm-cmvae" in result.stderr
    assert not (tmp_path / "run").exists()


def test_a_run_folder_holding_a_run_is_refused_before_any_service_starts(tmp_path: Path) -> None:
    """Refused last, after every other check, so `swimm up` from another folder got past its recipe's
    repo-relative encoder and sim settings file (found among swimm's own files) too."""
    run_dir, elsewhere = tmp_path / "run", tmp_path / "elsewhere"
    run_dir.mkdir()
    elsewhere.mkdir()
    (run_dir / "settings.json").write_text("{}")  # an earlier run's: a new one would overwrite its files
    for command in ("learn", "up"):
        result = swimm(command, "--run-dir", str(run_dir), "--steps", "10", cwd=elsewhere)
        assert result.returncode == SETTINGS_EXIT_CODE, result.stderr
        assert f"--run-dir {run_dir} already holds a run (settings.json): --resume one of its models" in result.stderr
    assert [path.name for path in run_dir.iterdir()] == ["settings.json"]  # no logs: nothing started
    assert not any(elsewhere.iterdir())
