"""`swimm learn` end to end on the in-process backend (real world, real SAC, tiny step counts): the run folder,
resuming, stopping, and the command line's refusals."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from stable_baselines3 import SAC

from encoder_service.model import CMVAE, make_checkpoint
from learner_service.checkpoints import load_for_resume, replay_buffer_path
from learner_service.command import LearnCommandSettings, RunResult, Training, check, check_new_run
from learner_service.envs import make_vec_env
from learner_service.identity import read_identity
from learner_service.learn_settings import DemoSettings, EvalSettings
from learner_service.progress import BEST_MODEL, BEST_MODEL_SCORE, FINAL_MODEL, latest_evaluation
from learner_service.task import TaskSettings
from services import settings as settings_mod
from swimm import cli

pytestmark = pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")

TINY_SAC = "{learning_starts: 50, gradient_steps: 1, batch_size: 32, buffer_size: 2000}"
STEPS = 200


def tiny_settings(run_dir: Path, **changes) -> LearnCommandSettings:
    settings = LearnCommandSettings(
        algo="sac",
        obs="state",
        backend="inprocess",
        steps=STEPS,
        seed=97,
        max_steps=40,
        run_dir=str(run_dir),
        hyperparams=TINY_SAC,
        checkpoint_every=100,
        eval=EvalSettings(episodes=1, min_steps=100, every=2, max_steps=20),
        log_interval_s=3600,
        progress_bar=False,
    )
    for name, value in changes.items():
        setattr(settings, name, value)
    return settings


@pytest.fixture(scope="module")
def first_run(tmp_path_factory) -> tuple[Path, RunResult]:
    run_dir = tmp_path_factory.mktemp("learn") / "run"
    return run_dir, Training(tiny_settings(run_dir)).run()


def monitor_endings(path: Path) -> Counter:
    episodes = pd.read_csv(path, skiprows=1)
    return Counter(episodes["cause"].fillna("").replace("", "time_limit"))


def test_run_folder_holds_the_run(first_run) -> None:
    run_dir, result = first_run
    assert STEPS <= result.num_timesteps < STEPS + 40  # SAC trains per episode, so it may finish the last one
    for name in ("settings.json", "train.monitor.csv", "progress.json", "result.json", "summary.png", FINAL_MODEL):
        assert (run_dir / name).is_file(), name
    assert (run_dir / "summary.png").read_bytes()[:4] == b"\x89PNG"
    assert list((run_dir / "tensorboard").rglob("events.out.tfevents.*"))
    assert (run_dir / "checkpoints" / "model_100_steps.zip").is_file()
    assert replay_buffer_path(run_dir / FINAL_MODEL).is_file()

    # The monitor CSV (written by SB3's VecMonitor from the env's infos) and the callback's counts agree.
    episodes = pd.read_csv(run_dir / "train.monitor.csv", skiprows=1)
    assert len(episodes) == result.episodes
    assert monitor_endings(run_dir / "train.monitor.csv") == Counter({k: v for k, v in result.endings.items() if v})
    assert episodes["l"].sum() <= result.num_timesteps

    saved = json.loads((run_dir / "settings.json").read_text())
    assert saved["settings"]["algo"] == "sac" and saved["resolved"]["steps"] == STEPS
    assert json.loads((run_dir / "result.json").read_text())["num_timesteps"] == result.num_timesteps
    assert json.loads((run_dir / "progress.json").read_text())["finished"] is True

    # Evaluations ran only past eval.min_steps, and the best one's model was kept.
    score = json.loads((run_dir / BEST_MODEL_SCORE).read_text())
    assert (run_dir / BEST_MODEL).is_file() and score["num_timesteps"] >= 100
    evaluations = pd.read_csv(run_dir / "evaluations.csv")
    assert (evaluations["num_timesteps"] >= 100).all()
    assert score["mean_return"] == pytest.approx(evaluations["mean_return"].max())
    assert evaluations["wall_s"].is_monotonic_increasing and (evaluations["wall_s"] > 0).all()
    steps, mean_return = latest_evaluation(run_dir)  # what `swimm up`'s bar shows
    assert steps == evaluations["num_timesteps"].iloc[-1] and mean_return == pytest.approx(
        evaluations["mean_return"].iloc[-1]
    )


def test_resume_continues_the_step_count_with_the_replay_buffer(first_run) -> None:
    run_dir, first = first_run
    env = make_vec_env("inprocess", TaskSettings(obs="state", max_steps=40), n_envs=1, base_seed=97)
    reloaded = load_for_resume("sac", run_dir / FINAL_MODEL, env)
    assert reloaded.num_timesteps == first.num_timesteps
    assert reloaded.replay_buffer.size() == first.num_timesteps  # every transition so far (buffer holds 2000)
    env.close()

    with pytest.raises(
        FileExistsError, match=r"already holds a run \(settings.json\): --resume one of its models to go on with it"
    ):
        check_new_run(tiny_settings(run_dir, steps=60))  # a new run there would overwrite the first one's files
    check_new_run(tiny_settings(run_dir, resume=str(run_dir / FINAL_MODEL), steps=60))
    resumed = Training(tiny_settings(run_dir, resume=str(run_dir / FINAL_MODEL), steps=60)).run()
    assert resumed.num_timesteps == first.num_timesteps + resumed.trained_steps
    assert resumed.trained_steps >= 60
    assert (run_dir / "train-2.monitor.csv").is_file()  # the first part's episodes stay in train.monitor.csv
    assert len(pd.read_csv(run_dir / "train-2.monitor.csv", skiprows=1)) == resumed.episodes


def test_sac_learns_the_3d_task_s_three_actions_from_the_tracker_s_demonstrations(tmp_path: Path) -> None:
    """The 3d task end to end: the scripted tracker's (surge, heave, yaw) demonstrations, SAC on three actions,
    evaluations with E and heave smoothness, and a model that records its task."""
    demo = DemoSettings(steps=100, bc_epochs=2, critic_steps=10)
    result = Training(tiny_settings(tmp_path / "run", task="3d", steps=300, demo=demo)).run()
    assert result.num_timesteps >= 300
    model = SAC.load(tmp_path / "run" / FINAL_MODEL, device="cpu")
    assert model.action_space.shape == (3,) and model.observation_space.shape == (12 + 10 * 3,)
    assert read_identity(tmp_path / "run" / FINAL_MODEL)["task"]["name"] == "3d"
    evaluations = pd.read_csv(tmp_path / "run" / "evaluations.csv")
    assert {"E", "S_H"} <= set(evaluations.columns) and (evaluations["S_H"] > 0).all()


def test_stop_request_still_saves_the_run(tmp_path: Path) -> None:
    stop = threading.Event()
    stop.set()  # as a SIGTERM before the first step would
    result = Training(tiny_settings(tmp_path / "run"), stop=stop).run()
    assert result.stopped_early and result.num_timesteps == 1
    assert (tmp_path / "run" / FINAL_MODEL).is_file()
    assert not (tmp_path / "run" / "summary.png").exists()  # no episode finished, so nothing to plot


def test_a_wall_time_budget_ends_training_and_saves(tmp_path: Path) -> None:
    settings = tiny_settings(tmp_path / "run", steps=100_000, budget_min=0.05)
    settings.eval.enabled = False
    result = Training(settings).run()
    assert 1 <= result.num_timesteps < 100_000 and result.wall_s < 60  # 3 s of budget, then the final save
    assert (tmp_path / "run" / FINAL_MODEL).is_file()


def test_flags_reach_the_settings() -> None:
    parser = cli.build_parser("learn")
    args = parser.parse_args(
        [
            "learn",
            "--algo",
            "td3",
            "--obs",
            "state",
            "--steps",
            "5",
            "--envs",
            "3",
            "--backend",
            "inprocess",
            "--eval-min-steps",
            "7",
            "--eval-unit",
            "steps",
            "--connect",
            "tcp/10.0.0.1:7447",
            "--namespace",
            "swimm/x",
        ]
    )
    settings = settings_mod.load(LearnCommandSettings, args, environ={})
    assert (settings.algo, settings.obs, settings.steps, settings.envs, settings.backend) == (
        "td3",
        "state",
        5,
        3,
        "inprocess",
    )
    assert (settings.eval.min_steps, settings.eval.unit) == (7, "steps")
    assert settings.zenoh.connect == ["tcp/10.0.0.1:7447"] and settings.zenoh.namespace == "swimm/x"


def test_hyperparams_come_inline_of_any_length_or_from_a_file(tmp_path: Path) -> None:
    from learner_service.command import parse_hyperparams

    block = "".join(f"key_{i}: {i}\n" for i in range(40))  # longer than a file name may be
    assert len(block) > 255 and parse_hyperparams(block) == {f"key_{i}": i for i in range(40)}
    (tmp_path / "h.yaml").write_text("gradient_steps: 32\n")
    assert parse_hyperparams(str(tmp_path / "h.yaml")) == {"gradient_steps": 32}
    with pytest.raises(ValueError, match="YAML mapping"):
        parse_hyperparams(str(tmp_path / "missing.yaml"))  # neither a file nor a mapping: named
    with pytest.raises(ValueError, match=r"--hyperparams '\{bad' is not YAML: expected ',' or '\}'.* column 5"):
        parse_hyperparams("{bad")
    (tmp_path / "bad.yaml").write_text("a: [1\n")
    with pytest.raises(ValueError, match=f"--hyperparams file {tmp_path / 'bad.yaml'} is not YAML: .* line 2"):
        parse_hyperparams(str(tmp_path / "bad.yaml"))


def test_refusals_name_what_to_change(tmp_path: Path) -> None:
    check(LearnCommandSettings(envs=2))  # SAC's per-episode training runs on several envs (learner_service/episodic.py)
    with pytest.raises(ValueError, match="gradient_steps -1"):
        check(LearnCommandSettings(envs=2, hyperparams="{gradient_steps: -1}"))
    with pytest.raises(ValueError, match="--budget-min -1: must be >= 0"):
        check(LearnCommandSettings(budget_min=-1))
    with pytest.raises(ValueError, match="backend"):
        check(LearnCommandSettings(backend="carrier-pigeon"))
    assert cli.main(["learn", "--algo", "scripted", "--run-dir", str(tmp_path / "x")]) == 2  # settings: exit 2
    assert not (tmp_path / "x").exists()


def test_any_sb3_api_class_trains_by_import_path(tmp_path: Path) -> None:
    settings = tiny_settings(tmp_path / "run", algo="stable_baselines3:A2C", hyperparams="{n_steps: 8}", steps=64)
    settings.eval.min_steps, settings.eval.unit, settings.eval.every = 32, "steps", 16
    result = Training(settings).run()
    assert result.num_timesteps == 64  # on-policy: 8 rollouts of 8 steps, exactly
    assert result.best_mean_return is not None and (tmp_path / "run" / BEST_MODEL).is_file()
    assert json.loads((tmp_path / "run" / "settings.json").read_text())["settings"]["algo"] == "stable_baselines3:A2C"


def test_inprocess_cmvae_trains_on_latents_of_a_given_encoder(tmp_path: Path) -> None:
    checkpoint = tmp_path / "tiny_cmvae.pt"  # untrained: the wiring (render, encode, learn) is under test
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    settings = tiny_settings(tmp_path / "run", obs="cmvae", encoder_checkpoint=str(checkpoint), steps=60)
    settings.eval.enabled = False
    result = Training(settings).run()
    episodes = pd.read_csv(tmp_path / "run" / "train.monitor.csv", skiprows=1)
    assert result.num_timesteps >= 60 and result.episodes == len(episodes)
    saved = SAC.load(tmp_path / "run" / FINAL_MODEL)
    assert saved.observation_space.shape == (30,)  # 10 latents + 10 previous (surge, yaw) actions


def test_inprocess_runs_train_and_evaluate_in_the_world_of_a_sim_settings_file(tmp_path: Path) -> None:
    """--sim-config gives in-process envs the world a sim started with the file serves (here: every episode under
    the murky preset), with the task's dolphin: the 3d task's, though the file names no motion."""
    sim_config = tmp_path / "sim.yaml"
    sim_config.write_text("noise_preset: murky\n")
    settings = tiny_settings(tmp_path / "run", obs="image", task="3d", sim_config=str(sim_config), steps=20)
    training = Training(settings)
    world = training.inprocess_world()
    assert world.noise.preset == "murky"
    env = make_vec_env("inprocess", training.task, n_envs=2, base_seed=5, world=world)
    plain = make_vec_env("inprocess", training.task, n_envs=2, base_seed=5)
    try:
        murky_world, plain_world = env.unwrapped.envs[0].world, plain.unwrapped.envs[0].world
        assert murky_world.settings.dolphin.motion == plain_world.settings.dolphin.motion == "3d"
        assert murky_world.settings.noise == world.noise and plain_world.settings.noise.preset == "off"
        murky_frames, plain_frames = env.reset()["image"], plain.reset()["image"]
        assert murky_frames.shape == plain_frames.shape and not np.array_equal(murky_frames, plain_frames)
    finally:
        env.close()
        plain.close()
    settings.eval.enabled = False
    assert Training(settings).run().num_timesteps >= 20


def test_a_sim_settings_file_is_refused_where_no_in_process_world_reads_it(tmp_path: Path) -> None:
    sim_config = tmp_path / "sim.yaml"
    sim_config.write_text("noise_preset: murky\n")
    with pytest.raises(ValueError, match="--sim-config .*sim.yaml: a running sim serves its own world"):
        check(LearnCommandSettings(sim_config=str(sim_config)))  # the zenoh backend: the sim is another process
    with pytest.raises(FileNotFoundError, match="--sim-config .*absent.yaml: no such settings file"):
        check(LearnCommandSettings(backend="inprocess", sim_config=str(tmp_path / "absent.yaml")))
    sim_config.write_text("noise_presett: murky\n")
    with pytest.raises(settings_mod.SettingsError, match="noise_presett"):
        check(tiny_settings(tmp_path / "run", sim_config=str(sim_config)))  # before any world is built


def test_the_bar_names_each_phase_in_order_with_its_own_count(tmp_path: Path, monkeypatch) -> None:
    """A tiny in-process run with the real callbacks and demonstrations, its bar drawn into a buffer: each phase
    in order, counted in its own units, and training's count starting from zero when training starts."""
    import io

    from learner_service import command
    from learner_service.learn_settings import DemoSettings
    from learner_service.progress import PhaseBar

    drawn = io.StringIO()
    # Not a stand-in: the real bar, drawn into a buffer, since under pytest stderr is no terminal and it would hide.
    monkeypatch.setattr(command, "PhaseBar", lambda disable: PhaseBar(file=drawn))
    demo = DemoSettings(steps=60, bc_epochs=2, critic_steps=150, bc_batch_size=32)
    Training(tiny_settings(tmp_path / "run", demo=demo, checkpoint_every=0)).run()
    frames = [frame.strip() for frame in drawn.getvalue().replace("\n", "\r").split("\r") if frame.strip()]
    phases = [frame.split(":")[0] for frame in frames]
    order = [phase for index, phase in enumerate(phases) if index == 0 or phases[index - 1] != phase]
    assert order[:5] == ["demonstrations", "cloning", "critic warm-up", "training", "evaluation"], order
    assert order[5] == "training" and set(order) == {"demonstrations", "cloning", "critic warm-up", "training",
                                                     "evaluation"}  # fmt: skip
    first = {phase: next(frame for frame in frames if frame.startswith(phase + ":")) for phase in order}
    assert "0/60" in first["demonstrations"] and "0/2" in first["cloning"] and "0/150" in first["critic warm-up"]
    assert f"0/{STEPS}" in first["training"] and "0/1" in first["evaluation"]
    assert "epoch" in first["cloning"] and "update" in first["critic warm-up"] and "episode" in first["evaluation"]
    progress = json.loads((tmp_path / "run" / "progress.json").read_text())
    assert progress["phase"] == "training" and progress["finished"] and progress["eval_timesteps"] >= 100
    # every phase entered stays in progress.json, so a launcher polling less often than phases change misses none
    entered = progress["phases_entered"]
    assert [phase for index, phase in enumerate(entered) if index == 0 or entered[index - 1] != phase] == order


def test_a_start_that_fails_before_training_leaves_the_run_folder_free_to_try_again(tmp_path: Path) -> None:
    """A world that cannot be built (no GL context for the image observation: GLX without a display) fails the
    run before it trains; its folder holds no run, so the same --run-dir takes the next attempt."""
    run_dir = tmp_path / "run"
    argv = ["learn", "--backend", "inprocess", "--steps", "50", "--run-dir", str(run_dir), "--no-progress-bar"]
    no_display = {key: value for key, value in os.environ.items() if key != "DISPLAY"} | {"MUJOCO_GL": "glx"}
    failed = subprocess.run([sys.executable, "-m", "swimm", *argv, "--obs", "image"], capture_output=True, text=True,
                            timeout=120, env=no_display)  # fmt: skip
    assert failed.returncode == 1, failed.stderr  # it passed the check: it failed once the run started
    assert not (run_dir / "settings.json").exists()
    assert cli.main([*argv, "--obs", "state"]) == 0
    assert (run_dir / "settings.json").is_file() and (run_dir / FINAL_MODEL).is_file()
