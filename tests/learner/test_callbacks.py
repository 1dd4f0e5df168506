"""The training callbacks on a real SB3 SAC learning on the real in-process world (state observations, tiny sizes).

Each check compares a callback's numbers with what was observed by another route: endings against a wrapper
that records what the env itself returned, the best model's score against a replay of its episodes.
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

from learner_service.callbacks import (
    BEST_MODEL,
    BEST_MODEL_SCORE,
    EVALUATIONS_CSV,
    CheckpointCallback,
    EpisodeStatsCallback,
    RolloutEvalCallback,
    StopOnEvent,
)
from learner_service.inprocess_env import TrackingEnv
from learner_service.learn_settings import EvalSettings
from learner_service.progress import replace_atomically
from learner_service.registry import make_model
from learner_service.task import TaskSettings
from sim_service.settings import WorldSettings

# Positions have no natural bound, so the state observation's Box is unbounded on purpose.
pytestmark = pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")

TINY_SAC = {"learning_starts": 50, "gradient_steps": 1, "batch_size": 32, "buffer_size": 2_000}
SHORT_EPISODES = TaskSettings(obs="state", max_steps=40)  # short enough that some episodes hit the time limit


class EndingRecorder(gym.Wrapper):
    """Writes down how each episode ended, from the env's own terminated/truncated flags and cause."""

    def __init__(self, env: gym.Env, endings: list[str]) -> None:
        super().__init__(env)
        self.endings = endings

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated:
            self.endings.append(info["cause"])
        elif truncated:
            self.endings.append("time_limit")
        return obs, reward, terminated, truncated, info


def state_env(task: TaskSettings, seed: int, endings: list[str] | None = None) -> gym.Env:
    env = TrackingEnv(task, WorldSettings(render=False), base_seed=seed)
    return EndingRecorder(env, endings) if endings is not None else env


def vec_env(task: TaskSettings, seeds: list[int], endings: list[str]) -> VecMonitor:
    return VecMonitor(DummyVecEnv([lambda s=s: state_env(task, s, endings) for s in seeds]), info_keywords=("cause",))


def test_endings_counted_as_the_env_reported_them() -> None:
    endings: list[str] = []
    env = vec_env(SHORT_EPISODES, [97, 98], endings)
    model = make_model("sac", env, seed=97, overrides=TINY_SAC | {"train_freq": [16, "step"]})  # 2 envs: steps
    stats = EpisodeStatsCallback(total_timesteps=400, log_interval_s=3600)
    model.learn(400, callback=stats)
    env.close()

    assert stats.episodes == len(endings) > 5
    assert {k: v for k, v in stats.endings.items() if v} == Counter(endings)
    assert stats.endings["time_limit"] > 0 and stats.endings["visibility"] > 0  # both kinds were seen
    assert stats.snapshot()["env_steps_per_s"] > 0
    assert len(stats.recent_returns) == min(stats.episodes, 20)


def test_eval_saves_best_model_only_after_min_steps(tmp_path: Path) -> None:
    endings: list[str] = []
    env = vec_env(SHORT_EPISODES, [97], endings)
    eval_task = TaskSettings(obs="state", max_steps=30, early_termination=False)
    eval_env = state_env(eval_task, 113)
    schedule = EvalSettings(episodes=2, min_steps=250, every=1, unit="episodes", seed=113, max_steps=30)
    model = make_model("sac", env, seed=97, overrides=TINY_SAC)
    evaluation = RolloutEvalCallback(eval_env, schedule, tmp_path)
    seen_before_min: list[bool] = []

    class WatchBestModel(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps < schedule.min_steps:
                seen_before_min.append((tmp_path / BEST_MODEL).exists())
            return True

    model.learn(500, callback=[evaluation, WatchBestModel()])

    assert seen_before_min and not any(seen_before_min)
    table = pd.read_csv(tmp_path / EVALUATIONS_CSV)
    assert len(table) == evaluation.evaluations >= 2
    assert (table["num_timesteps"] >= schedule.min_steps).all()
    score = json.loads((tmp_path / BEST_MODEL_SCORE).read_text())
    assert score["mean_return"] == pytest.approx(table["mean_return"].max())
    best_row = table.loc[table["mean_return"].idxmax()]
    assert score["num_timesteps"] == best_row["num_timesteps"]
    assert score["model_sha256"] == hashlib.sha256((tmp_path / BEST_MODEL).read_bytes()).hexdigest()
    assert not list(tmp_path.glob("*.partial"))  # each best model was written aside and renamed into place

    # Replaying the saved best model on the same seed by hand gives the returns the callback recorded.
    best = SAC.load(tmp_path / BEST_MODEL)
    returns = []
    obs, _ = eval_env.reset(seed=schedule.seed)
    for episode in range(schedule.episodes):
        if episode:
            obs, _ = eval_env.reset()
        total, done = 0.0, False
        while not done:
            action, _ = best.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = eval_env.step(action)
            total, done = total + reward, terminated or truncated
        returns.append(total)
    recorded = [float(value) for value in best_row["returns"].split()]
    assert returns == pytest.approx(recorded, abs=1e-3)
    assert score["mean_return"] == pytest.approx(np.mean(returns), abs=1e-3)
    env.close()
    eval_env.close()


def test_a_replaced_file_keeps_its_old_bytes_until_the_new_ones_are_complete(tmp_path: Path) -> None:
    """What `swimm eval --watch` relies on when it copies best_model.zip while the learner saves a newer one."""
    path = tmp_path / BEST_MODEL
    path.write_bytes(b"old model")
    seen_while_writing: list[bytes] = []

    def write(partial: Path) -> None:
        partial.write_bytes(b"new mod")
        seen_while_writing.append(path.read_bytes())
        partial.write_bytes(b"new model")

    replace_atomically(path, write)
    assert seen_while_writing == [b"old model"]
    assert path.read_bytes() == b"new model" and not list(tmp_path.glob("*.partial"))


def test_checkpoints_every_n_steps_keep_the_newest_replay_buffer(tmp_path: Path) -> None:
    env = vec_env(SHORT_EPISODES, [97, 98], [])
    model = make_model("sac", env, seed=97, overrides=TINY_SAC | {"train_freq": [16, "step"]})
    model.learn(300, callback=CheckpointCallback(every=100, save_path=tmp_path, n_envs=2))
    env.close()

    models = sorted(path.name for path in tmp_path.glob("model_*_steps.zip"))
    assert models == ["model_100_steps.zip", "model_200_steps.zip", "model_300_steps.zip"]
    assert [path.name for path in tmp_path.glob("*.pkl")] == ["model_replay_buffer_300_steps.pkl"]
    assert SAC.load(tmp_path / "model_200_steps.zip").num_timesteps == 200


def test_stop_event_ends_training_at_the_next_step() -> None:
    env = vec_env(SHORT_EPISODES, [97], [])
    model = make_model("sac", env, seed=97, overrides=TINY_SAC)
    stop = threading.Event()

    class StopAt(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == 30:
                stop.set()
            return True

    model.learn(1_000, callback=[StopAt(), StopOnEvent(stop)])
    env.close()
    assert model.num_timesteps == 30


def test_evaluations_of_the_3d_task_record_e_and_heave_smoothness(tmp_path: Path) -> None:
    train_task, eval_task = (TaskSettings(obs="state", task="3d", max_steps=40, early_termination=early)
                             for early in (True, False))  # fmt: skip
    env = VecMonitor(DummyVecEnv([lambda: TrackingEnv(train_task, base_seed=97)]), info_keywords=("cause",))
    eval_env = TrackingEnv(eval_task, base_seed=113)
    schedule = EvalSettings(episodes=1, min_steps=0, every=50, unit="steps", seed=113, max_steps=40)
    model = make_model("sac", env, seed=97, overrides=TINY_SAC)
    model.learn(100, callback=RolloutEvalCallback(eval_env, schedule, tmp_path))
    table = pd.read_csv(tmp_path / EVALUATIONS_CSV)
    assert table.columns[-3:].tolist() == ["E", "S_H", "returns"] and (table["E"] > 0).all()
    assert (table["S_H"] > 0).all()
    best = table.loc[table["mean_return"].idxmax()]
    assert json.loads((tmp_path / BEST_MODEL_SCORE).read_text())["E"] == pytest.approx(best["E"])
    env.close()
    eval_env.close()
