"""`swimm up` as a real process tree: router, sim, encoder and learner processes talking over Zenoh, training SAC
for a few hundred steps, leaving a run folder, and stopping every process it started (also on SIGTERM)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch

from encoder_service.model import CMVAE, make_checkpoint
from services.keys import Keys
from services.presence import live_now
from services.procs import Service
from swimm import cli

TINY_SAC = "{learning_starts: 50, gradient_steps: 1, batch_size: 32, buffer_size: 2000}"


def up_args(run_dir: Path, namespace: str, *extra: str) -> list[str]:
    return ["--port", "0", "--namespace", namespace, "--run-dir", str(run_dir), "--hyperparams", TINY_SAC,
            "--max-steps", "100", "--log-interval-s", "5", "--demo-steps", "0", *extra]  # fmt: skip


def wait_exit(service: Service, timeout_s: float) -> int:
    try:
        return service.process.wait(timeout=timeout_s)
    except Exception:
        pytest.fail(f"swimm up did not finish within {timeout_s} s; its log ends:\n{service.log_tail(60)}")


def started_pids(service: Service) -> dict[str, int]:
    """The processes `swimm up` says it started, by name, from its own log."""
    return {name: int(pid) for name, pid in re.findall(r"started (\S+) \(pid (\d+)\)", service.log_path.read_text())}


def is_running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def assert_all_stopped(service: Service, expected: set[str]) -> None:
    pids = started_pids(service)
    assert set(pids) == expected, service.log_tail(60)
    assert not [name for name, pid in pids.items() if is_running(pid)]


@pytest.mark.slow
def test_up_trains_on_cmvae_and_leaves_a_run_folder(spawn, namespace, tmp_path) -> None:
    checkpoint = tmp_path / "tiny_cmvae.pt"  # an untrained CMVAE: the pipeline, not the policy, is under test
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    run_dir = tmp_path / "run"
    sim_config = tmp_path / "sim.yaml"
    sim_config.write_text("noise_preset: murky\nnoise_randomise: true\n")
    up = spawn("up", *up_args(run_dir, namespace, "--steps", "300", "--encoder-checkpoint", str(checkpoint),
                              "--sim-config", str(sim_config)))  # fmt: skip
    assert wait_exit(up, 150) == 0, up.log_tail(60)
    assert "image noise: murky: randomised up to (fog 0.12" in (run_dir / "logs" / "sim.log").read_text()

    assert_all_stopped(up, {"router", "sim", "encoder", "learner"})
    result = json.loads((run_dir / "result.json").read_text())
    assert result["num_timesteps"] >= 300 and not result["stopped_early"]
    episodes = pd.read_csv(run_dir / "train.monitor.csv", skiprows=1)
    assert len(episodes) == result["episodes"] > 0
    assert (run_dir / "summary.png").read_bytes()[:4] == b"\x89PNG"
    for name in ("final_model.zip", "settings.json", "learn.yaml", "logs/sim.log", "logs/encoder.log"):
        assert (run_dir / name).is_file(), name
    assert list((run_dir / "tensorboard").rglob("events.out.tfevents.*"))
    learner_log = (run_dir / "logs" / "learner.log").read_text()
    assert "1 zenoh env(s), obs cmvae" in learner_log  # it trained through the services, on latents
    assert "processes joined as peers" in up.log_path.read_text()  # the default topology: direct links


@pytest.mark.slow
def test_up_stops_everything_on_sigterm_and_keeps_the_model(spawn, namespace, tmp_path) -> None:
    run_dir = tmp_path / "run"
    # --low-latency reaches every process it starts: a link takes that transport only when both ends ask.
    up = spawn("up", *up_args(run_dir, namespace, "--obs", "state", "--steps", "1000000", "--low-latency"))
    deadline = time.monotonic() + 100
    while time.monotonic() < deadline:
        progress = run_dir / "progress.json"
        if progress.is_file() and json.loads(progress.read_text())["num_timesteps"] >= 100:
            break
        assert up.alive, up.log_tail(60)
        time.sleep(0.5)
    else:
        pytest.fail(f"no training progress within 100 s:\n{up.log_tail(60)}")

    up.process.send_signal(signal.SIGTERM)
    assert wait_exit(up, 90) == 0, up.log_tail(60)
    assert_all_stopped(up, {"router", "sim", "learner"})  # state observations: no encoder
    result = json.loads((run_dir / "result.json").read_text())
    assert result["stopped_early"] and 100 <= result["num_timesteps"] < 1_000_000
    assert (run_dir / "final_model.zip").is_file() and (run_dir / "train.monitor.csv").is_file()
    ending = up.log_tail(12)  # a stopped run's last lines: what it saved, and how to go on
    assert "final_model.zip (+ final_model_replay_buffer.pkl, its replay buffer)" in ending, ending
    assert f"resume training: swimm up --config {run_dir / 'up.yaml'} --resume {run_dir / 'final_model.zip'}" in ending
    for name in ("router", "sim", "learner"):
        assert "low-latency transport" in (run_dir / "logs" / f"{name}.log").read_text(), name


@pytest.mark.slow
def test_up_splits_the_envs_between_sims_and_steps_them_in_groups(spawn, namespace, tmp_path) -> None:
    run_dir = tmp_path / "run"
    # SAC's per-episode training (gradient_steps 1 per episode here) on 4 envs: the EpisodicTraining path.
    up = spawn("up", *up_args(run_dir, namespace, "--obs", "state", "--steps", "400", "--envs", "4", "--sims", "2"))
    assert wait_exit(up, 150) == 0, up.log_tail(60)
    assert_all_stopped(up, {"router", "sim-0", "sim-1", "learner"})
    result = json.loads((run_dir / "result.json").read_text())
    assert result["num_timesteps"] >= 400 and result["episodes"] > 0
    learner_settings = json.loads((run_dir / "settings.json").read_text())["settings"]
    assert learner_settings["envs"] == 4 and learner_settings["group_size"] == 2  # one group per sim
    assert "2 gradient step" not in (run_dir / "logs" / "learner.log").read_text()
    assert "1 gradient step(s) after every 1 finished episode(s)" in (run_dir / "logs" / "learner.log").read_text()
    for index in (0, 1):
        sim_log = (run_dir / "logs" / f"sim-{index}.log").read_text()
        assert f"sim sim-{index} serving 2 train and {2 if index == 0 else 0} eval envs" in sim_log


@pytest.mark.slow
def test_up_names_each_phase_of_a_short_run_in_order(spawn, namespace, tmp_path) -> None:
    """Without a terminal `swimm up` logs a line at each phase the learner enters: the head start's phases, then
    training (with evaluations between), each with its own count."""
    run_dir = tmp_path / "run"
    up = spawn("up", *up_args(run_dir, namespace, "--obs", "state", "--steps", "1500", "--eval-min-steps", "500",
                              "--eval-every", "500", "--eval-unit", "steps", "--eval-episodes", "1",
                              "--eval-max-steps", "1500"),  # long enough for the launcher's 0.5 s polls to see
               "--demo-steps", "600", "--demo-teacher", "scripted", "--demo-bc-epochs", "400",
               "--demo-critic-steps", "2000")  # fmt: skip
    assert wait_exit(up, 240) == 0, up.log_tail(60)
    log_text = up.log_path.read_text()
    shown = re.findall(r"learner: ([a-z -]+) (\d+)/(\d+) (\w+)", log_text)
    # a phase begun and ended between two of the launcher's polls gets a line without its count
    phases = re.findall(r"learner: ([a-z -]+?) (?:\d+/\d+ \w+|\(begun and ended between two looks\))", log_text)
    order = [phase for index, phase in enumerate(phases) if index == 0 or phases[index - 1] != phase]
    assert order[:4] == ["demonstrations", "cloning", "critic warm-up", "training"], shown
    assert "evaluation" in order[4:], shown
    totals = {phase: (int(total), unit) for phase, _, total, unit in shown}
    assert totals["demonstrations"] == (600, "steps") and totals["cloning"] == (400, "epochs")
    assert totals["critic warm-up"] == (2000, "updates") and totals["evaluation"] == (1, "episodes")
    assert totals["training"] == (1500, "steps")


def test_up_refuses_a_missing_sim_config_before_starting_anything(tmp_path, capfd) -> None:
    missing = tmp_path / "nowhere.yaml"
    assert cli.main(["up", "--run-dir", str(tmp_path / "run"), "--sim-config", str(missing)]) == 2
    message = capfd.readouterr().err
    assert f"--sim-config {missing}: no such settings file" in message
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--envs", "3", "--sims", "2"], "divide --envs into equal shares"),
        (["--envs", "4", "--sims", "0"], "--sims 0: must be >= 1"),
        (["--envs", "8", "--sims", "2", "--group-size", "3"], "--group-size 3 does not divide the 4 envs"),
    ],
)
def test_up_refuses_sims_that_cannot_share_the_envs(tmp_path, capfd, flags, message) -> None:
    assert cli.main(["up", "--obs", "state", "--run-dir", str(tmp_path / "run"), *flags]) == 2
    assert message in capfd.readouterr().err
    assert not (tmp_path / "run").exists()


def test_up_refuses_an_unknown_encoder_engine_by_flag_and_by_variable(tmp_path, capfd, monkeypatch) -> None:
    with pytest.raises(SystemExit) as stopped:
        cli.main(["up", "--obs", "state", "--run-dir", str(tmp_path / "run"), "--encoder-engine", "tensorrt"])
    assert stopped.value.code == 2 and "--encoder-engine: invalid choice: 'tensorrt'" in capfd.readouterr().err
    monkeypatch.setenv("SWIMM_ENCODER_ENGINE", "tensorrt")  # the variable a deployment sets
    assert cli.main(["up", "--obs", "state", "--run-dir", str(tmp_path / "run")]) == 2
    assert "SWIMM_ENCODER_ENGINE: setting 'encoder_engine' got 'tensorrt'" in capfd.readouterr().err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--steps", "-5"], "up refused its settings: --steps -5: must be >= 0"),
        (["--envs", "-1"], "up refused its settings: --envs -1: must be >= 1"),
        (["--eval-episodes", "0"], "up refused its settings: --eval-episodes 0: must be >= 1"),
        (["--port", "70000"], "up refused its settings: --port 70000: must be <= 65535"),
        (["--sim-config", "SIM_YAML"], "setting 'train_envs' got -3: must be >= 0"),
        (["--algo", "scripted"], "up refused its settings: a scripted baseline has nothing to learn"),
    ],
)
def test_up_refuses_bad_settings_before_any_process_or_folder(tmp_path, flags, message) -> None:
    """A real `swimm up`: the refusal names the flag as typed, its value and range, exits 2 at once, and
    nothing was started (no log says so) or made (no run folder)."""
    sim_yaml = tmp_path / "sim.yaml"
    sim_yaml.write_text("train_envs: -3\n")  # a setting of the sim it would start
    flags = [str(sim_yaml) if flag == "SIM_YAML" else flag for flag in flags]
    argv = [sys.executable, "-m", "swimm", "up", "--run-dir", str(tmp_path / "run"), "--obs", "state", *flags]
    started = time.monotonic()
    result = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "started" not in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "run").exists()
    assert time.monotonic() - started < 60


def test_up_without_the_cmvae_says_what_to_do(tmp_path, capfd) -> None:
    missing = tmp_path / "nope.pt"
    assert cli.main(["up", "--encoder-checkpoint", str(missing), "--run-dir", str(tmp_path / "run")]) == 2
    message = capfd.readouterr().err
    assert "--obs state" in message and str(missing) in message
    assert not (tmp_path / "run").exists()  # nothing was started


def wait_for_steps(up: Service, run_dir: Path, steps: int, timeout_s: float = 120) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        progress = run_dir / "progress.json"
        if progress.is_file() and json.loads(progress.read_text())["num_timesteps"] >= steps:
            return
        assert up.alive, up.log_tail(60)
        time.sleep(0.5)
    pytest.fail(f"not {steps} training steps within {timeout_s} s:\n{up.log_tail(60)}")


@pytest.mark.slow
def test_up_restarts_a_killed_encoder_and_sim_and_training_goes_on(spawn, namespace, tmp_path) -> None:
    checkpoint = tmp_path / "tiny_cmvae.pt"
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    run_dir = tmp_path / "run"
    up = spawn("up", *up_args(run_dir, namespace, "--steps", "3000", "--encoder-checkpoint", str(checkpoint),
                              "--restart-backoff-s", "1"))  # fmt: skip
    wait_for_steps(up, run_dir, 300)
    os.kill(started_pids(up)["encoder"], signal.SIGKILL)
    wait_for_steps(up, run_dir, 1000)
    os.kill(started_pids(up)["sim"], signal.SIGKILL)
    assert wait_exit(up, 240) == 0, up.log_tail(60)

    log = up.log_path.read_text()
    for name in ("encoder", "sim"):
        assert f"{name} exited with -9: restarted" in log, log
    assert_all_stopped(up, {"router", "sim", "encoder", "learner"})
    result = json.loads((run_dir / "result.json").read_text())
    assert result["num_timesteps"] >= 3000 and not result["stopped_early"]
    learner_log = (run_dir / "logs" / "learner.log").read_text()
    assert "the sim lost the episode" in learner_log and "claiming the env again" in learner_log
    episodes = pd.read_csv(run_dir / "train.monitor.csv", skiprows=1)
    assert episodes["l"].sum() <= result["num_timesteps"]  # no step counted twice across the restarts


@pytest.mark.slow
def test_up_past_its_restart_limit_ends_the_run_and_keeps_the_model(spawn, namespace, tmp_path) -> None:
    run_dir = tmp_path / "run"
    up = spawn("up", *up_args(run_dir, namespace, "--obs", "state", "--steps", "1000000", "--restart-limit", "0"))
    wait_for_steps(up, run_dir, 100)
    os.kill(started_pids(up)["sim"], signal.SIGKILL)
    assert wait_exit(up, 120) != 0
    assert "sim exited with -9; its log ends" in up.log_path.read_text()
    assert (run_dir / "final_model.zip").is_file()
    assert_all_stopped(up, {"router", "sim", "learner"})


@pytest.mark.slow
def test_up_restarts_a_killed_sim_whose_envs_step_in_groups(spawn, namespace, tmp_path) -> None:
    run_dir = tmp_path / "run"
    up = spawn("up", *up_args(run_dir, namespace, "--obs", "state", "--envs", "4", "--group-size", "2",
                              "--steps", "3000", "--restart-backoff-s", "1"))  # fmt: skip
    wait_for_steps(up, run_dir, 400)
    os.kill(started_pids(up)["sim"], signal.SIGKILL)
    assert wait_exit(up, 240) == 0, up.log_tail(60)
    assert "sim exited with -9: restarted" in up.log_path.read_text()
    learner_log = (run_dir / "logs" / "learner.log").read_text()
    assert learner_log.count("the sim lost the episode") >= 4  # each env of both groups (and maybe the eval env)
    assert json.loads((run_dir / "result.json").read_text())["num_timesteps"] >= 3000


@pytest.mark.slow
def test_up_restarts_a_killed_router_and_training_goes_on(spawn, namespace, zenoh_session, tmp_path) -> None:
    """The router only introduces the peers: with it dead they go on stepping to one another, and the restarted
    router (the same port) takes the sessions back."""
    run_dir = tmp_path / "run"
    up = spawn("up", *up_args(run_dir, namespace, "--obs", "state", "--steps", "3000", "--restart-backoff-s", "1"))
    wait_for_steps(up, run_dir, 300)
    os.kill(started_pids(up)["router"], signal.SIGKILL)
    wait_for_steps(up, run_dir, 1500)
    endpoint = re.search(r"router at (tcp/\S+),", up.log_path.read_text()).group(1)
    observer = zenoh_session(endpoint)  # joins the new router: it must know the sim and the learner again
    deadline = time.monotonic() + 30
    while not (live_now(observer, Keys(namespace), "sim") and live_now(observer, Keys(namespace), "learner")):
        assert time.monotonic() < deadline, "the sim and the learner never came back to the restarted router"
    assert wait_exit(up, 240) == 0, up.log_tail(60)
    assert "router exited with -9: restarted" in up.log_path.read_text()
    assert_all_stopped(up, {"router", "sim", "learner"})
    assert json.loads((run_dir / "result.json").read_text())["num_timesteps"] >= 3000
