"""`swimm eval` pieces on the in-process backend: contenders, the run folder, the live view, the watch loop.

Everything runs for real: MuJoCo worlds, an SB3 SAC checkpoint saved and loaded from disk, the HTTP server.
The checks recompute the numbers the evaluator wrote by a different route (from the per-step CSV's raw
columns: theta, d, the actions, the frustum flag) rather than comparing against stored values.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import threading
import urllib.parse
import urllib.request
from dataclasses import replace
from pathlib import Path

import matplotlib.image
import numpy as np
import pandas as pd
import pytest

from encoder_service import DEFAULT_CHECKPOINT
from eval_service import command, engine, sweep, watch
from eval_service.attach import NoEvalEnv, free_env_ids
from eval_service.command import EvalCommandSettings
from eval_service.engine import contenders, evaluate
from eval_service.live import LiveFeed, LiveView, tap_frames
from eval_service.report import RunFolder
from eval_service.sweep import SweepSettings
from learner_service.export import SHIPPED_POLICY
from learner_service.identity import policy_identity, stamp
from learner_service.inprocess_env import TrackingEnv
from learner_service.metrics import SMOOTHNESS_WEIGHTS, EpisodeMetrics, summarise
from learner_service.registry import make_model
from learner_service.task import TaskSettings
from services.geometry import ALPHA_DEG, BETA_DEG, MAX_D, OPT_D
from services.identity import IDENTITY_ROW_FIELDS, episode_identity
from services.messages import InfoReply
from services.results import file_sha256
from services.settings import SETTINGS_EXIT_CODE, ZenohSettings
from sim_service.latency import LatencySettings
from sim_service.noise import PRESETS
from sim_service.pod import PodParams
from sim_service.settings import PodSettings, WorldSettings
from swimm.cli import main as swimm

STEPS = 60
EPISODES = 2


def settings(tmp_path: Path, **overrides) -> EvalCommandSettings:
    base = EvalCommandSettings(backend="inprocess", obs="state", episodes=EPISODES, steps=STEPS, seed=131,
                               progress_bar=False, figures=False, out=str(tmp_path / "out"))  # fmt: skip
    return replace(base, **overrides)


def untrained_sac(folder: Path, task: str = "planar") -> Path:
    """An untrained SAC on the task's state observation, saved like `swimm learn` saves: a real checkpoint to load."""
    env = TrackingEnv(TaskSettings(obs="state", task=task), WorldSettings(render=False))
    model = make_model("sac", env, seed=5, overrides={"buffer_size": 1000})
    stamp(model, policy_identity("", "state", "swimm2", task))
    path = folder / "best_model.zip"
    model.save(path)
    env.close()
    return path


@pytest.fixture(scope="module")
def sac_checkpoint(tmp_path_factory) -> Path:
    return untrained_sac(tmp_path_factory.mktemp("ckpt"))


def test_contenders_pair_algorithms_with_checkpoints_in_order() -> None:
    entries = contenders(EvalCommandSettings(algo=["sac", "scripted", "td3"], checkpoint=["a/s.zip", "b/t.zip"]))
    assert [(e.label, e.algo, e.checkpoint) for e in entries] == [
        ("sac", "sac", "a/s.zip"), ("scripted", "scripted", None), ("td3", "td3", "b/t.zip")
    ]  # fmt: skip
    same_algo = contenders(EvalCommandSettings(checkpoint=["run1/best_model.zip", "run2/best_model.zip"]))
    assert [e.label for e in same_algo] == ["sac:run1/best_model", "sac:run2/best_model"]
    # no checkpoint: the shipped policy on cmvae (what a bare `swimm eval` plays), the scripted baseline elsewhere
    assert [(e.algo, e.checkpoint) for e in contenders(EvalCommandSettings())] == [("sac", str(SHIPPED_POLICY))]
    assert [(e.algo, e.checkpoint) for e in contenders(EvalCommandSettings(algo=["scripted", "sac"]))] == [
        ("scripted", None), ("sac", str(SHIPPED_POLICY))
    ]  # fmt: skip
    assert [e.algo for e in contenders(EvalCommandSettings(obs="state"))] == ["scripted"]
    assert [e.label for e in contenders(EvalCommandSettings(algo=["scripted"], label=["baseline"]))] == ["baseline"]


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"algo": ["td3"]}, "needs a --checkpoint"),
        ({"algo": ["sac"], "obs": "state"}, "needs a --checkpoint"),  # the shipped policy is for cmvae only
        ({"algo": ["scripted"], "checkpoint": ["x.zip"]}, "without an --algo"),
        ({"algo": ["nope"], "checkpoint": ["x.zip"]}, "unknown algorithm"),
        ({"algo": ["scripted", "sac"], "checkpoint": ["x.zip"], "label": ["same", "same"]}, "distinct"),
    ],
)
def test_contenders_refuse_what_cannot_pair(given, message) -> None:
    with pytest.raises(ValueError, match=message):
        contenders(EvalCommandSettings(**given))


def test_settings_are_checked_before_anything_starts(tmp_path) -> None:
    for bad in ({"noise": "maybe"}, {"backend": "carrier-pigeon"}, {"obs": "sonar"}, {"episodes": 0}):
        with pytest.raises(ValueError):
            command.check(settings(tmp_path, **bad))
    missing = {"checkpoint": [str(tmp_path / "gone.zip")]}, {"encoder_checkpoint": "gone.pt", "backend": "zenoh"}
    for bad, message in zip(
        missing, ("--checkpoint .*gone.zip: no such file", "--encoder-checkpoint gone.pt"), strict=True
    ):
        with pytest.raises(FileNotFoundError, match=message):  # at once, not after a wait for a live sim
            command.check(settings(tmp_path, algo=["sac"], **bad))


def test_a_file_that_is_no_policy_and_a_mismatched_pair_are_refused_before_any_wait(tmp_path) -> None:
    """Over Zenoh (the default) both used to wait a minute for a router and then report the router."""
    text = tmp_path / "notes.zip"
    text.write_text("not a model")
    with pytest.raises(ValueError, match=f"{text} is not a policy checkpoint"):
        command.check(settings(tmp_path, backend="zenoh", algo=["sac"], checkpoint=[str(text)]))
    mismatched = settings(
        tmp_path,
        backend="zenoh",
        obs="cmvae",
        algo=["sac"],
        checkpoint=[str(SHIPPED_POLICY)],
        encoder_checkpoint=str(DEFAULT_CHECKPOINT),
    )  # the clean CMVAE, not the policy's
    with pytest.raises(ValueError, match=f"policy {SHIPPED_POLICY} was trained on encoder .*but the encoder given is"):
        command.check(mismatched)


def eval_env(env: str, holder: str | None) -> InfoReply:
    return InfoReply("eval", env, holder, ep=0, seq=0, sim="sim-1", image_size=64)


def test_no_live_sim_and_no_free_env_are_clear_errors() -> None:
    zenoh = ZenohSettings(connect=["tcp/10.0.0.1:7447"], namespace="swimm/x")
    with pytest.raises(NoEvalEnv, match=r"no live sim serves swimm/x/eval/\* \(connected to tcp/10.0.0.1:7447\)"):
        free_env_ids([], zenoh)
    held = [eval_env("0", "eval-abc"), eval_env("1", "eval-def")]
    with pytest.raises(NoEvalEnv, match="eval/0 by eval-abc, eval/1 by eval-def"):
        free_env_ids(held, zenoh)
    free = [eval_env(env, None) for env in ("2", "10", "9")]
    assert free_env_ids([*held, *free], zenoh) == ["10", "9", "2"]  # eval/0 stays for a learner's own evaluation


def _recomputed_episode(steps: pd.DataFrame) -> dict[str, float]:
    """Table 12 terms of one episode straight from the raw per-step columns, with the SPEC's formulas."""
    actions = steps[["surge", "yaw_cmd"]].to_numpy()
    smooth = np.zeros(2)
    for t in range(1, len(actions)):
        previous = actions[max(0, t - 10) : t][::-1]
        smooth += 0.5 * (np.abs(actions[t] - previous) * SMOOTHNESS_WEIGHTS[: len(previous), None]).sum(axis=0)
    return {
        "return": steps["reward"].sum(),
        "A": np.minimum(steps["theta"].abs(), ALPHA_DEG).mean() / ALPHA_DEG,
        "D": (steps["d"] - OPT_D).abs().mean() / MAX_D,
        "S_D": smooth[0] / len(actions),
        "S_A": smooth[1] / len(actions),
        "left_view": not steps["in_frustum"].all(),
    }


def test_evaluation_run_folder_holds_consistent_numbers(tmp_path, sac_checkpoint) -> None:
    given = settings(tmp_path, algo=["scripted", "sac"], checkpoint=[str(sac_checkpoint)], figures=True)
    summaries = evaluate(given, Path(given.out))
    out = Path(given.out)
    for name in ("steps.csv", "episodes.csv", "summary.json", "returns.png", "metrics.png",
                 "trajectory-scripted.png", "trajectory-sac.png"):  # fmt: skip
        assert (out / name).is_file(), name
    steps = pd.read_csv(out / "steps.csv", keep_default_na=False)
    episodes = pd.read_csv(out / "episodes.csv")
    assert len(steps) == 2 * EPISODES * STEPS
    assert list(summaries) == ["scripted", "sac"]
    # the same seeds for every contender: identical episode seeds and identical starting poses
    seeds = episodes.pivot(index="episode", columns="label", values="seed")
    assert (seeds["scripted"] == seeds["sac"]).all() and seeds["scripted"].nunique() == EPISODES
    for (label, episode), rows in steps.groupby(["label", "episode"]):
        row = episodes[(episodes["label"] == label) & (episodes["episode"] == episode)].iloc[0]
        assert rows["step"].tolist() == list(range(1, STEPS + 1))  # no early termination in evaluation
        for name, value in _recomputed_episode(rows).items():
            assert row[name] == pytest.approx(value, rel=1e-9, abs=1e-12), (label, episode, name)
    for label, summary in summaries.items():
        mine = episodes[episodes["label"] == label]
        assert summary["mean_return"] == pytest.approx(mine["return"].mean())
        assert summary["A'"] == pytest.approx(mine["left_view"].mean())
    written = json.loads((out / "summary.json").read_text())
    assert written["labels"] == json.loads(json.dumps(summaries))
    assert written["paper SAC"]["mean_return"] == 2.40e3
    # the second contender's return against the first's, on the same episodes
    returns = episodes.pivot(index="episode", columns="label", values="return")
    ratio = written["return_ratios"]["sac"]
    assert ratio["of"] == "scripted" and ratio["episodes"] == EPISODES
    assert ratio["ratio"] == pytest.approx(returns["sac"].mean() / returns["scripted"].mean())
    assert ratio["ci95"][0] <= ratio["ratio"] <= ratio["ci95"][1]
    # deterministic: the scripted baseline plays its episodes again identically
    again = evaluate(replace(given, algo=["scripted"], checkpoint=[], out=str(tmp_path / "again")), tmp_path / "again")
    assert again["scripted"] == summaries["scripted"]
    assert json.loads((tmp_path / "again" / "summary.json").read_text())["return_ratios"] == {}  # nothing to pair


def test_cli_prints_the_table_beside_the_paper(tmp_path, capsys) -> None:
    out = tmp_path / "cli"
    code = swimm(["eval", "--backend", "inprocess", "--obs", "state", "--algo", "scripted", "--episodes", "1",
                  "--steps", "20", "--out", str(out), "--no-progress-bar", "--no-figures"])  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())["labels"]["scripted"]
    assert f"{summary['mean_return']:11.3g}" in printed.splitlines()[1]
    assert printed.splitlines()[2].startswith("paper SAC")

    first = (out / "summary.json").read_bytes()
    again = ["eval", "--backend", "inprocess", "--obs", "state", "--algo", "scripted", "--episodes", "1", "--steps",
             "7", "--out", str(out), "--no-progress-bar", "--no-figures"]  # fmt: skip
    assert swimm(again) == SETTINGS_EXIT_CODE  # refused: it would overwrite the first evaluation
    assert (out / "summary.json").read_bytes() == first
    assert swimm([*again, "--overwrite"]) == 0
    assert len(pd.read_csv(out / "steps.csv")) == 7


def test_a_3d_evaluation_reports_the_elevation_error_and_heave_beside_table_12(tmp_path, capsys) -> None:
    out = tmp_path / "3d"
    code = swimm(["eval", "--backend", "inprocess", "--obs", "state", "--task", "3d", "--algo", "scripted",
                  "--episodes", "1", "--steps", str(STEPS), "--out", str(out), "--no-progress-bar"])  # fmt: skip
    assert code == 0
    header, scripted, paper = capsys.readouterr().out.splitlines()[:3]
    summary = json.loads((out / "summary.json").read_text())["labels"]["scripted"]
    steps = pd.read_csv(out / "steps.csv")
    episode = pd.read_csv(out / "episodes.csv").iloc[0]
    elevation_error = np.minimum(steps["elevation"].abs(), BETA_DEG).mean() / BETA_DEG
    assert summary["E"] == pytest.approx(elevation_error) and episode["E"] == pytest.approx(elevation_error)
    assert summary["E"] > 0.0  # the dolphin swims off the rover's depth at once
    assert steps["d"].to_numpy() == pytest.approx(np.hypot(np.hypot(steps["target_x"] - steps["rover_x"],
                                                                    steps["target_y"] - steps["rover_y"]),
                                                           steps["target_z"] - steps["rover_z"]))  # fmt: skip
    assert header.split()[-2:] == ["E", "S_H"] and f"{summary['E']:11.3g}" in scripted and paper.endswith("-")
    assert (steps["heave"] != 0).any() and summary["S_H"] == pytest.approx(steps["S_H"].mean()) == episode["S_H"]
    assert (out / "metrics.png").is_file() and (out / "depth-scripted.png").is_file()


def _get(url: str) -> tuple[str, bytes]:
    with urllib.request.urlopen(url, timeout=10) as reply:
        return reply.headers["Content-Type"], reply.read()


def test_live_view_serves_the_latest_frame_and_episode_metrics(tmp_path) -> None:
    feed = LiveFeed()
    given = settings(tmp_path, episodes=1, steps=30)
    with LiveView(feed) as view:
        evaluate(given, Path(given.out), feed=feed)
        kind, page = _get(view.url)
        assert kind.startswith("text/html") and b"/api/state" in page
        (source,) = json.loads(_get(view.url + "api/sources")[1])
        assert source == "scripted @ inprocess"
        query = "?source=" + urllib.parse.quote(source)
        state = json.loads(_get(view.url + "api/state" + query)[1])
        kind, png = _get(view.url + "frame.png" + query)
    steps = pd.read_csv(Path(given.out) / "steps.csv")
    assert state["frame"] == 30 and state["has_image"] is True
    assert state["step"]["step"] == 30 and state["step"]["d"] == pytest.approx(steps["d"].iloc[-1])
    assert state["episode"]["A"] == pytest.approx(steps["A"].mean())
    assert state["episode"]["S_A"] == pytest.approx(steps["S_A"].mean())
    assert kind == "image/png"
    (tmp_path / "frame.png").write_bytes(png)
    image = matplotlib.image.imread(tmp_path / "frame.png")
    assert image.shape == (64, 64, 3) and image.std() > 0.01  # a rendered underwater frame, not a blank


def test_the_live_view_keeps_the_running_e_of_a_3d_episode_only() -> None:
    feed = LiveFeed()
    flags = {"in_frustum": True, "distance_exceeded": False, "collided": False}
    terms = {"A": 0.0, "D": 0.0, "S_D": 0.0, "S_A": 0.0}
    for step, e in enumerate((0.2, 0.4), start=1):
        feed.update("3d", {"label": "x", "episode": 1, "step": step, **flags, **terms, "E": e})
        feed.update("planar", {"label": "x", "episode": 1, "step": step, **flags, **terms})
    assert feed.state("3d")["episode"]["E"] == pytest.approx(0.3)
    assert "E" not in feed.state("planar")["episode"]


def test_watch_scores_each_new_best_model_once_and_stops_when_training_ends(tmp_path, sac_checkpoint) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "settings.json").write_text(json.dumps({"settings": {"algo": "sac", "obs": "state", "reward": "swimm2"}}))
    (run / watch.BEST_MODEL).write_bytes(sac_checkpoint.read_bytes())
    (run / watch.BEST_MODEL_SCORE).write_text(json.dumps({"num_timesteps": 1234, "mean_return": 1.0}))
    (run / watch.RUN_FINISHED).write_text("{}")
    given = settings(tmp_path, obs="cmvae", episodes=1, steps=20, watch=str(run), watch_interval_s=0.05)
    out = tmp_path / "watched"
    scored = watch.watch(given, run, out, None, None, interval_s=0.05, stop=threading.Event())
    assert scored == 1
    table = pd.read_csv(out / watch.WATCH_TABLE)
    assert table["num_timesteps"].tolist() == [1234]
    summary = json.loads((out / "step-1234" / "summary.json").read_text())
    assert summary["num_timesteps"] == 1234 and summary["settings"]["obs"] == "state"  # the run's obs, not ours
    assert table["mean_return"].iloc[0] == pytest.approx(summary["labels"]["sac@1234"]["mean_return"])
    assert (out / "checkpoints" / "best-1234.zip").read_bytes() == sac_checkpoint.read_bytes()


def test_watch_evaluates_a_3d_run_on_the_3d_task(tmp_path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    trained = {"algo": "sac", "obs": "state", "reward": "swimm2", "task": "3d"}
    (run / "settings.json").write_text(json.dumps({"settings": trained}))
    (run / watch.BEST_MODEL).write_bytes(untrained_sac(tmp_path, task="3d").read_bytes())
    (run / watch.BEST_MODEL_SCORE).write_text(json.dumps({"num_timesteps": 99, "mean_return": 1.0}))
    (run / watch.RUN_FINISHED).write_text("{}")
    given = settings(tmp_path, episodes=1, steps=20, watch=str(run))
    watch.watch(given, run, tmp_path / "watched", None, None, interval_s=0.05, stop=threading.Event())
    summary = json.loads((tmp_path / "watched" / "step-99" / "summary.json").read_text())
    assert summary["settings"]["task"] == "3d" and "E" in summary["labels"]["sac@99"]


def test_watcher_waits_for_a_best_model_and_takes_each_version_once(tmp_path) -> None:
    run, copies = tmp_path / "run", tmp_path / "copies"
    run.mkdir()
    watcher = watch.BestModelWatcher(run, copies)
    assert watcher.poll() is None and not watcher.finished  # nothing saved yet
    (run / watch.BEST_MODEL).write_bytes(b"first")
    (run / watch.BEST_MODEL_SCORE).write_text("{not json")  # half-written JSON is ignored until whole
    assert watcher.poll() is None
    (run / watch.BEST_MODEL_SCORE).write_text(json.dumps({"num_timesteps": 10}))
    assert watcher.poll() == (10, copies / "best-10.zip")
    assert watcher.poll() is None
    (run / watch.BEST_MODEL).write_bytes(b"second")
    (run / watch.BEST_MODEL_SCORE).write_text(json.dumps({"num_timesteps": 20}))
    assert watcher.poll() == (20, copies / "best-20.zip")
    assert (copies / "best-10.zip").read_bytes() == b"first" and (copies / "best-20.zip").read_bytes() == b"second"


def test_watcher_keeps_a_copy_only_when_its_hash_is_the_one_the_score_gives(tmp_path) -> None:
    """The learner replaced the zip after the watcher read the JSON, and has not yet written the new JSON: the
    copy is of the newer model, so it must not be scored as the older version."""
    run, copies = tmp_path / "run", tmp_path / "copies"
    run.mkdir()
    watcher = watch.BestModelWatcher(run, copies)

    def save(model: bytes, version: int, recorded: bytes) -> None:
        (run / watch.BEST_MODEL).write_bytes(model)
        score = {"num_timesteps": version, "model_sha256": hashlib.sha256(recorded).hexdigest()}
        (run / watch.BEST_MODEL_SCORE).write_text(json.dumps(score))

    save(b"second", 10, recorded=b"first")  # the JSON of version 10, the zip already version 20's
    assert watcher.poll() is None and not (copies / "best-10.zip").exists()
    save(b"second", 20, recorded=b"second")
    assert watcher.poll() == (20, copies / "best-20.zip")
    assert (copies / "best-20.zip").read_bytes() == b"second"


def test_each_noise_choice_renders_the_same_episode_through_its_noise_in_process(tmp_path) -> None:
    frames, applied = {}, {}
    for choice in ("keep", "off", "on", "murky", "harsh"):
        with engine.evaluation_env(settings(tmp_path, noise=choice), render=True) as env:
            frame = tap_frames(env)
            option = engine.noise_option(choice)
            env.reset(seed=113, options=None if option is None else {"noise": option})
            env.step(np.zeros(2, np.float32))
            frames[choice], applied[choice] = frame().astype(np.int16), env.world.noise_settings
    assert applied["keep"] is None and applied["off"] is None  # an in-process world starts clean
    assert applied["on"] == applied["murky"] == dataclasses.replace(PRESETS["murky"], preset="off")
    assert applied["harsh"] == dataclasses.replace(PRESETS["harsh"], preset="off")
    assert np.array_equal(frames["keep"], frames["off"])
    for noisy in ("murky", "harsh"):
        assert np.abs(frames[noisy] - frames["off"]).mean() > 1.0  # same seed and action, visibly different pixels


def test_a_sweep_plays_every_condition_once_and_writes_its_table_and_figure(tmp_path) -> None:
    given = settings(tmp_path, obs="cmvae", algo=["sac", "scripted"], checkpoint=[str(SHIPPED_POLICY)], episodes=1,
                     steps=40, sweep=True, figures=True,
                     sweep_plan=SweepSettings(severities=[0.0, 1.0, 2.0], effects=["all", "fog"]))  # fmt: skip
    table = sweep.sweep(given, given.sweep_plan, Path(given.out))
    conditions = [("none", 0.0), ("all", 1.0), ("all", 2.0), ("fog", 1.0), ("fog", 2.0)]
    for label in ("sac", "scripted"):
        rows = table[table["label"] == label]
        assert list(zip(rows["effects"], rows["severity"], strict=True)) == conditions
    episodes = pd.read_csv(Path(given.out) / "episodes.csv")
    assert len(episodes) == 10 and episodes["seed"].nunique() == 1  # every condition plays the same episode
    assert table["mean_return"].tolist() == pytest.approx(episodes["return"].tolist())
    # Noise reaches a policy only through its frames: the camera policy's actions change, ground truth's do not.
    scripted, camera = table[table["label"] == "scripted"], table[table["label"] == "sac"]
    assert scripted["mean_return"].nunique() == 1
    assert camera["mean_return"].iloc[0] != camera["mean_return"].iloc[2]
    image = matplotlib.image.imread(Path(given.out) / "sweep.png")
    assert image.shape[0] > 200 and image.std() > 0.01


def test_a_3d_sweep_adds_e_to_its_table(tmp_path) -> None:
    given = settings(tmp_path, task="3d", algo=["scripted"], episodes=1, steps=20, sweep=True,
                     sweep_plan=SweepSettings(severities=[0.0, 1.0], effects=["fog"]))  # fmt: skip
    table = sweep.sweep(given, given.sweep_plan, Path(given.out))
    episodes = pd.read_csv(Path(given.out) / "episodes.csv")
    assert table["E"].tolist() == pytest.approx(episodes["E"].tolist()) and (table["E"] > 0).all()


def test_a_latency_sweep_delays_and_holds_what_the_policy_commands(tmp_path) -> None:
    plan = SweepSettings(kind="latency", delays_ms=[0.0, 160.0], rates_hz=[50.0, 10.0])
    given = settings(tmp_path, algo=["scripted"], episodes=1, steps=60, sweep=True, figures=True, sweep_plan=plan)
    table = sweep.sweep(given, plan, Path(given.out))
    assert list(zip(table["effects"], table["severity"], strict=True)) == [
        ("delay", 0.0),
        ("delay", 160.0),
        ("rate", 50.0),
        ("rate", 10.0),
    ]
    undelayed, late, full_rate, slow = table["mean_return"].tolist()
    assert undelayed == full_rate  # 0 ms and 50 Hz are the same loop
    assert late != undelayed and slow != undelayed  # ground truth's actions arrive late, or once every 5 steps
    image = matplotlib.image.imread(Path(given.out) / "sweep.png")
    assert image.shape[0] > 200 and image.std() > 0.01


def test_eval_latency_flags_reach_the_world_and_default_to_leaving_it(tmp_path) -> None:
    assert engine.reset_options(settings(tmp_path)) == {}
    delayed = settings(tmp_path, latency=LatencySettings(observation_delay=4), noise="murky")
    assert engine.reset_options(delayed) == {
        "noise": {"preset": "murky"},
        "latency": {"observation_delay": 4, "action_delay": 0, "control_period": 1, "randomise": False},
    }


def test_a_pod_evaluation_reports_identity_beside_table_12_and_a_lone_dolphins_does_not(tmp_path, capsys) -> None:
    out = tmp_path / "pod"
    crossing_step = round(PodParams().crossing_period_s / 4 / WorldSettings().physics_dt)
    code = swimm(["eval", "--backend", "inprocess", "--obs", "state", "--algo", "scripted", "--episodes", "1",
                  "--steps", str(crossing_step + 20), "--dolphin-pod-size", "4", "--dolphin-pod-crossing",
                  "--out", str(out), "--no-progress-bar", "--no-figures"])  # fmt: skip
    assert code == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header.split()[-4:] == ["identity_kept", "identity_share", "switches", "reacquire_steps"]
    steps, episode = pd.read_csv(out / "steps.csv"), pd.read_csv(out / "episodes.csv").iloc[0]
    assert steps["target_occluded"].iloc[crossing_step - 1]  # the crossing companion is in front of the target
    recomputed = episode_identity(steps["followed"].tolist(), steps["target_occluded"].tolist())
    assert {name: episode[name] for name in IDENTITY_ROW_FIELDS} == pytest.approx(recomputed, nan_ok=True)
    summary = json.loads((out / "summary.json").read_text())["labels"]["scripted"]
    assert summary["identity_kept"] == float(recomputed["identity_kept"])
    lone = tmp_path / "lone"
    assert swimm(["eval", "--backend", "inprocess", "--obs", "state", "--algo", "scripted", "--episodes", "1",
                  "--steps", "20", "--out", str(lone), "--no-progress-bar", "--no-figures"]) == 0  # fmt: skip
    assert "followed" not in pd.read_csv(lone / "steps.csv") and "switches" not in pd.read_csv(lone / "episodes.csv")


def test_a_pods_episodes_scored_without_steps_keep_their_identity_columns(tmp_path) -> None:
    """As `swimm eval --recording` writes a run folder: episode rows only, no step CSV rows."""
    metrics = EpisodeMetrics("train/0", 1)
    for identity in ((0, False), (1, True), (0, False)):
        metrics.add(6.0, 0.0, True, False, (0.0, 0.0), 1.0, identity=identity)
    folder = RunFolder(tmp_path / "offline")
    folder.add_episode(metrics.row() | {"seed": None, "steps": metrics.steps})
    folder.finish({"train/0": summarise([metrics])}, {}, {}, None)
    episodes = pd.read_csv(tmp_path / "offline" / "episodes.csv")
    assert tuple(episodes.columns[-len(IDENTITY_ROW_FIELDS) :]) == IDENTITY_ROW_FIELDS
    assert episodes["identity_share"].tolist() == [1.0] and episodes["occlusions"].tolist() == [1]
    assert pd.read_csv(tmp_path / "offline" / "steps.csv").columns[0] == "label"  # the header, with no rows


def test_a_pod_is_the_in_process_worlds_a_live_sim_has_its_own(tmp_path) -> None:
    with pytest.raises(ValueError, match="--dolphin-pod-\\* build the in-process world's pod: start the live sim"):
        command.check(settings(tmp_path, backend="zenoh", pod=PodSettings(size=4)))
    with pytest.raises(ValueError, match="--dolphin-pod-crossing needs a companion to cross"):
        command.check(settings(tmp_path, pod=PodSettings(crossing=True)))


def test_a_sim_settings_file_builds_the_in_process_world_and_is_recorded(tmp_path) -> None:
    world_file = tmp_path / "world.yaml"
    world_file.write_text("render_scale: 2\ndolphin_pod_size: 3\nnoise_preset: murky\n")
    given = settings(tmp_path, sim_config=str(world_file))
    with engine.evaluation_env(given, render=True) as env:
        env.reset(seed=113)
        assert env.world.settings.render_scale == 2 and env.world.settings.dolphin.pod_size == 3
        assert env.world.noise_settings.fog > 0  # the file's murky water, which --noise keep leaves
    with engine.evaluation_env(replace(given, pod=PodSettings(size=2))) as env:
        assert env.world.settings.dolphin.pod_size == 2  # the flags' pod over the file's
    recorded = engine.run_provenance(given, [])["sim_config"]
    assert recorded == {"path": str(world_file), "sha256": file_sha256(world_file)}
    with pytest.raises(ValueError, match="--sim-config .* builds the in-process world: a live sim serves its own"):
        command.check(replace(given, backend="zenoh"))
    with pytest.raises(FileNotFoundError, match="--sim-config .*missing.yaml: no such settings file"):
        command.check(settings(tmp_path, sim_config=str(tmp_path / "missing.yaml")))


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("noise_preset: muddy\n", "unknown noise preset 'muddy'"),
        ("scene_preset: reef\n", "unknown scene preset 'reef'"),
        ("dolphin_pod_size: 1\ndolphin_pod_crossing: true\n", "--dolphin-pod-crossing needs a companion"),
        ("image_size: 0\n", "image_size"),
    ],
)
def test_a_sim_settings_file_the_sim_would_refuse_is_refused_at_the_check(tmp_path, line, message) -> None:
    """Refused by the file's name before any world is built or a policy loaded (not "eval failed" later)."""
    world_file = tmp_path / "world.yaml"
    world_file.write_text(line)
    with pytest.raises(ValueError, match=f"--sim-config {world_file}.*{message}|{world_file}.*{message}"):
        command.check(settings(tmp_path, sim_config=str(world_file)))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"sweep_plan": SweepSettings(kind="weather")}, "--sweep-kind must be one of noise, latency"),  # type: ignore[arg-type]
        ({"sweep_plan": SweepSettings(kind="latency", rates_hz=[30.0])}, "--sweep-rates-hz must divide the sim's 50"),
        ({"sweep_plan": SweepSettings(kind="latency", delays_ms=[-20.0])}, "--sweep-delays-ms must be >= 0"),
        ({"sweep_plan": SweepSettings(kind="latency", delays_ms=[], rates_hz=[])}, "needs --sweep-delays-ms"),
        ({"latency": LatencySettings(control_period=0)}, "control_period >= 1"),
        ({"sweep_plan": SweepSettings(preset="fish")}, "--sweep-preset"),
        ({"sweep_plan": SweepSettings(effects=["smoke"])}, "--sweep-effects"),
        ({"sweep_plan": SweepSettings(severities=[-1.0])}, "--sweep-severities"),
        ({"watch": "runs/x"}, "--sweep and --watch are two different runs"),
        ({"noise": "soup"}, "--noise must be one of keep, off, on, murky, harsh"),
    ],
)
def test_bad_sweep_and_noise_settings_are_refused_by_name(tmp_path, overrides, message) -> None:
    with pytest.raises(ValueError, match=message):
        command.check(settings(tmp_path, sweep=True, **overrides))


def test_the_camera_only_scripted_tracker_follows_from_the_latent_alone(tmp_path) -> None:
    """It reads the shipped CMVAE's decoded d and theta, never the telemetry: close to the ground-truth tracker
    on clean frames, and it moves with the image where the ground-truth one cannot (the noise sweep uses this)."""
    given = settings(tmp_path, obs="cmvae", algo=["scripted", "scripted-camera"], episodes=1, steps=300)
    summaries = evaluate(given, Path(given.out))
    camera, truth = summaries["scripted-camera"], summaries["scripted"]
    assert camera["A'"] == camera["D'"] == camera["C'"] == 0.0
    assert camera["mean_return"] > 0.8 * truth["mean_return"] and camera["mean_return"] != truth["mean_return"]
    tracker = engine.load_policies(given, engine.contenders(given))["scripted-camera"]
    with pytest.raises(ValueError, match="cmvae observations"):
        tracker.act({"image": np.zeros((64, 64, 3), np.uint8)}, {})
    with pytest.raises(ValueError, match="needs --obs cmvae"):
        engine.load_policies(replace(given, obs="state"), engine.contenders(given))
