"""`swimm eval` attaches to a sim that a learner is training on, and the training does not notice.

Real processes: a router, a sim serving train/0 and eval/0, and `swimm eval` as its own process. The
learner here is a ProxyEnv on train/0 driven by a fixed action sequence (what a learner's env sees does not
depend on how the actions were chosen). It replays the same seeded episodes again and again while the
evaluator plays its episode on eval/0 of the same sim process; every pass must give exactly the telemetry of
a pass made before the evaluator existed.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import matplotlib.image
import msgpack
import numpy as np
import pandas as pd
import pytest

from eval_service.live import LiveFeed
from eval_service.live_tap import EnvTap
from learner_service.proxy_env import ProxyEnv, ProxySettings
from learner_service.task import TaskSettings
from services.control import survey
from services.geometry import ALPHA_DEG, relative_geometry
from services.keys import Keys
from sim_service.pod import PodParams
from sim_service.settings import WorldSettings
from swimm.cli import main as swimm
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

SEED = 97
TRAIN_STEPS = 250
EVAL_STEPS = 200
CROSSING_STEP = round(PodParams().crossing_period_s / 4 / WorldSettings().physics_dt)  # the crossing split's first
TASK = TaskSettings(obs="state", max_steps=100)  # short episodes: the passes cross resets and early endings too


def fixed_actions() -> np.ndarray:
    rng = np.random.default_rng(3)
    actions = np.clip(rng.normal([0.3, 0.0], [0.4, 0.4], (TRAIN_STEPS, 2)), -1, 1)
    actions[100:150, 1] = 1.0  # a hard spin: loses the dolphin, so an episode ends early
    return actions.astype(np.float32)


def training_pass(proxy: ProxySettings) -> tuple[list[tuple], float, float]:
    """(telemetry, reward, terminated, truncated, stepped) per step of one pass from SEED (stepped is False for
    the observations of resets), and the pass's start and end times."""
    started = time.time()
    env = ProxyEnv(TASK, proxy, "0", base_seed=SEED)
    try:
        obs, info = env.reset(seed=SEED)
        steps: list[tuple] = [(info["telemetry"], 0.0, False, False, False)]
        for action in fixed_actions():
            obs, reward, terminated, truncated, info = env.step(action)
            steps.append((info["telemetry"], reward, terminated, truncated, True))
            if terminated or truncated:
                obs, info = env.reset()
                steps.append((info["telemetry"], 0.0, False, False, False))
    finally:
        env.close()
    return steps, started, time.time()


def eval_args(router: str, namespace: str, out: Path) -> list[str]:
    return ["--connect", router, "--namespace", namespace, "--algo", "scripted", "--episodes", "1", "--steps",
            str(EVAL_STEPS), "--obs", "state", "--out", str(out), "--no-progress-bar", "--no-figures"]  # fmt: skip


def test_eval_attaches_beside_training_without_changing_it(
    group, zenoh_router, namespace, zenoh_settings, zenoh_session, tmp_path
) -> None:
    start_sim(group, zenoh_router, namespace)
    # a generous step timeout: a reset is one control request, not retried, and this machine is shared and busy
    proxy = ProxySettings(zenoh_settings(zenoh_router), channel="train", role="learner", step_timeout_s=10.0)
    baseline, _, _ = training_pass(proxy)
    assert any(row[2] for row in baseline), "the fixed actions should end an episode early"

    session = zenoh_session(zenoh_router)
    published: list[dict] = []
    subscriber = session.declare_subscriber(
        Keys(namespace).metrics("eval", "*"),
        lambda sample: published.append(msgpack.unpackb(sample.payload.to_bytes())),
    )
    out = tmp_path / "eval"
    evaluator = group.start("eval", "eval", *eval_args(zenoh_router, namespace, out))
    passes = []
    deadline = time.monotonic() + 120
    while evaluator.process.poll() is None and time.monotonic() < deadline:
        passes.append(training_pass(proxy))
    assert evaluator.process.wait(timeout=max(1.0, deadline - time.monotonic())) == 0, evaluator.log_tail()
    passes.append(training_pass(proxy))  # and after it left
    subscriber.undeclare()

    for index, (steps, _, _) in enumerate(passes):
        assert steps == baseline, f"training pass {index} differs from the pass without an evaluator"
    eval_steps = pd.read_csv(out / "steps.csv")
    assert eval_steps["step"].tolist() == list(range(1, EVAL_STEPS + 1))
    eval_window = (eval_steps["t"].min(), eval_steps["t"].max())
    overlapping = [p for p in passes if p[1] < eval_window[1] and p[2] > eval_window[0]]
    assert overlapping, f"no training pass ran while the evaluator stepped ({len(passes)} passes)"

    summary = json.loads((out / "summary.json").read_text())
    assert summary["env"] == "eval/0"
    scripted = summary["labels"]["scripted"]
    assert scripted["mean_return"] == pytest.approx(eval_steps["reward"].sum())
    kinds = {message["kind"]: message for message in published}
    assert set(kinds) == {"episode", "summary"}
    assert kinds["summary"]["mean_return"] == pytest.approx(scripted["mean_return"])
    (eval_env,) = [info for info in survey(session, Keys(namespace).ctl("eval", "*")) if info.env == "0"]
    assert eval_env.holder is None and eval_env.seq == EVAL_STEPS  # it released the env when done


def test_a_pod_sims_identity_ground_truth_reaches_eval_as_in_process(group, zenoh_router, namespace, tmp_path) -> None:
    """A live sim's pod (--dolphin-pod-*) and the in-process world's give `swimm eval` the same identity columns."""
    pod = ["--dolphin-pod-size", "4", "--dolphin-pod-crossing"]
    start_sim(group, zenoh_router, namespace, *pod)
    steps = ["--steps", str(CROSSING_STEP + 20)]
    live, inprocess = tmp_path / "live", tmp_path / "inprocess"
    evaluator = group.start("eval", "eval", *eval_args(zenoh_router, namespace, live), *steps)
    assert evaluator.process.wait(timeout=120) == 0, evaluator.log_tail()
    assert (
        swimm(["eval", *eval_args(zenoh_router, namespace, inprocess)[4:], *steps, "--backend", "inprocess", *pod]) == 0
    )
    live_steps, inprocess_steps = pd.read_csv(live / "steps.csv"), pd.read_csv(inprocess / "steps.csv")
    identity = ["followed", "target_occluded"]
    assert live_steps[identity].equals(inprocess_steps[identity]) and live_steps["target_occluded"].any()
    assert (
        pd.read_csv(live / "episodes.csv")
        .drop(columns="label")
        .equals(pd.read_csv(inprocess / "episodes.csv").drop(columns="label"))
    )


def test_eval_says_who_holds_the_only_eval_env(group, zenoh_router, namespace, zenoh_settings, tmp_path) -> None:
    start_sim(group, zenoh_router, namespace)
    holder = ProxyEnv(TASK, ProxySettings(zenoh_settings(zenoh_router), channel="eval", role="eval"), "0")
    holder.reset(seed=SEED)  # it drives the env, so the sim answers before the evaluator starts
    try:
        evaluator = group.start("eval", "eval", *eval_args(zenoh_router, namespace, tmp_path / "refused"))
        assert evaluator.process.wait(timeout=120) == 1
    finally:
        holder.close()
    assert f"every eval env is held (eval/0 by {holder.holder})" in evaluator.log_tail()
    assert not (tmp_path / "refused" / "steps.csv").exists()


def test_live_view_taps_the_training_env_without_driving_it(
    group, zenoh_router, namespace, zenoh_settings, tmp_path
) -> None:
    start_sim(group, zenoh_router, namespace)
    zenoh = zenoh_settings(zenoh_router)
    proxy = ProxySettings(zenoh, channel="train", role="learner", step_timeout_s=10.0)
    feed = LiveFeed()
    tap = EnvTap(zenoh, "train/0", feed)
    try:
        time.sleep(1.0)  # let the tap's subscriptions reach the router before the first step
        steps, _, _ = training_pass(proxy)
        deadline = time.monotonic() + 10
        while (feed.state("train/0") or {}).get("episode", {}).get("steps") != _last_episode_steps(steps):
            assert time.monotonic() < deadline, f"the tap saw {feed.state('train/0')}"
            time.sleep(0.1)
    finally:
        tap.close()
    state = feed.state("train/0")
    last = max(i for i, row in enumerate(steps) if row[4])
    episode = steps[last - _last_episode_steps(steps) + 1 : last + 1]
    geometry = [relative_geometry(row[0]) for row in episode]
    assert state["step"]["d"] == pytest.approx(geometry[-1].d, abs=1e-12)
    assert state["step"]["reward"] == pytest.approx(episode[-1][1], abs=1e-12)  # the learner's own reward
    assert state["step"]["return_so_far"] == pytest.approx(sum(row[1] for row in episode))
    assert state["episode"]["A"] == pytest.approx(np.mean([min(abs(g.theta), ALPHA_DEG) / ALPHA_DEG for g in geometry]))
    assert state["has_image"]
    image = matplotlib.image.imread(io.BytesIO(feed.png("train/0")), format="png")
    assert image.shape == (64, 64, 3)


def _last_episode_steps(steps: list[tuple]) -> int:
    """How many stepped rows the last episode of a pass has (after its last reset)."""
    count = 0
    for row in reversed(steps):
        if row[4]:
            count += 1
        elif count:
            break
    return count


def test_watch_scores_each_best_model_of_a_live_training_run(
    group, zenoh_router, namespace, zenoh_session, tmp_path
) -> None:
    """`swimm learn` (its own evaluation callback on eval/0) and `swimm eval --watch` (on eval/1) side by side."""
    start_sim(group, zenoh_router, namespace, "--eval-envs", "2")
    session = zenoh_session(zenoh_router)
    published: list[dict] = []
    subscriber = session.declare_subscriber(
        Keys(namespace).metrics("eval", "*"), lambda s: published.append(msgpack.unpackb(s.payload.to_bytes()))
    )
    run, out = tmp_path / "run", tmp_path / "watched"
    network = ["--connect", zenoh_router, "--namespace", namespace, "--obs", "state", "--no-progress-bar"]
    learner = group.start("learn", "learn", *network, "--algo", "sac", "--steps", "800", "--max-steps", "200",
                          "--eval-min-steps", "0", "--eval-every", "2", "--eval-episodes", "1",
                          "--eval-max-steps", "100", "--hyperparams", "{learning_starts: 100, gradient_steps: 4}",
                          "--checkpoint-every", "0", "--run-dir", str(run))  # fmt: skip
    deadline = time.monotonic() + 60
    while not run.is_dir():
        assert time.monotonic() < deadline and learner.alive, learner.log_tail()
        time.sleep(0.2)
    watcher = group.start("watch", "eval", *network, "--watch", str(run), "--episodes", "1", "--steps", "100",
                          "--watch-interval-s", "0.5", "--out", str(out), "--no-figures")  # fmt: skip
    assert learner.process.wait(timeout=300) == 0, learner.log_tail()
    assert watcher.process.wait(timeout=120) == 0, watcher.log_tail()  # it stops by itself once training is over
    subscriber.undeclare()

    # the learner's own scores (evaluation callback, same seed 113 and length) for each model the watcher took
    learner_scores = pd.read_csv(run / "evaluations.csv").set_index("num_timesteps")["mean_return"]
    watched = pd.read_csv(out / "watch.csv")
    assert len(watched) >= 2, f"only {len(watched)} best models scored:\n{watcher.log_tail()}"
    for version, mean_return in zip(watched["num_timesteps"], watched["mean_return"], strict=True):
        assert mean_return == learner_scores[version], f"model at {version} steps scored differently"
    final_best = json.loads((run / "best_model.json").read_text())["num_timesteps"]
    assert watched["num_timesteps"].iloc[-1] == final_best  # the last best model is never missed
    summaries = [m for m in published if m["kind"] == "summary"]
    assert [m["num_timesteps"] for m in summaries] == watched["num_timesteps"].tolist()
    assert "attached to " + namespace + "/eval/1" in (tmp_path / "logs" / "watch.log").read_text()
