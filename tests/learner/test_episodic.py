"""Per-episode training on several envs (learner_service/episodic.py) with a real SB3 SAC on the real world.

The count of gradient steps is checked against the episodes a VecMonitor saw end, and against SB3's own
per-episode loop on one env: a finished episode buys the same gradient steps either way.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

from learner_service.checkpoints import load_for_resume
from learner_service.episodic import EpisodicTraining, episodic_schedule, vectorised_kwargs
from learner_service.inprocess_env import TrackingEnv
from learner_service.registry import make_model, training_callbacks
from learner_service.task import TaskSettings
from sim_service.settings import WorldSettings

pytestmark = pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")

SHORT_EPISODES = TaskSettings(obs="state", max_steps=30)
PER_EPISODE = {"train_freq": [1, "episode"], "gradient_steps": 3, "learning_starts": 0, "batch_size": 16,
               "buffer_size": 2_000, "device": "cpu", "stats_window_size": 10_000}  # fmt: skip


def vec_env(n_envs: int) -> VecMonitor:
    factories = [
        lambda seed=seed: TrackingEnv(SHORT_EPISODES, WorldSettings(render=False), base_seed=seed)
        for seed in range(97, 97 + n_envs)
    ]
    return VecMonitor(DummyVecEnv(factories))


def critic_weights(model) -> np.ndarray:
    return torch.cat([p.detach().flatten() for p in model.critic.parameters()]).numpy().copy()


def test_several_envs_take_the_gradient_steps_of_every_finished_episode() -> None:
    env = vec_env(3)
    model = make_model("sac", env, seed=97, overrides=PER_EPISODE)
    assert (model.train_freq.frequency, model.gradient_steps) == (64, 0)  # gSDE: rollouts of sde_sample_freq steps
    callbacks = training_callbacks("sac", PER_EPISODE, env.num_envs)
    assert len(callbacks) == 1 and isinstance(callbacks[0], EpisodicTraining)
    before = critic_weights(model)
    model.learn(300, callback=callbacks)
    episodes = len(model.ep_info_buffer)
    assert episodes >= 8
    assert callbacks[0].gradient_steps_taken == 3 * episodes
    assert not np.allclose(before, critic_weights(model))  # the gradient steps really trained the critic
    env.close()


def test_one_env_keeps_stable_baselines3s_own_episodic_loop() -> None:
    assert training_callbacks("sac", PER_EPISODE, 1) == []
    assert vectorised_kwargs(PER_EPISODE, 1) == PER_EPISODE
    assert vectorised_kwargs(PER_EPISODE | {"train_freq": [64, "step"]}, 1)["train_freq"] == [64, "step"]


@pytest.mark.parametrize(
    ("train_freq", "gradient_steps", "n_envs", "expected"),
    [
        ([512, "step"], 64, 8, ((64, "step"), 64)),  # the SPEC's TD3: every 512 env steps, 64 gradient steps
        ([100, "step"], 64, 8, ((12, "step"), 61)),  # 96 env steps between trainings: 64 * 96 / 100 gradient steps
        (4, 1, 8, ((1, "step"), 2)),  # one vector step is 8 env steps: two trainings' worth
    ],
)
def test_a_step_schedule_counts_env_steps_whatever_the_envs(train_freq, gradient_steps, n_envs, expected) -> None:
    kwargs = vectorised_kwargs({"train_freq": train_freq, "gradient_steps": gradient_steps}, n_envs)
    assert (kwargs["train_freq"], kwargs["gradient_steps"]) == expected


def test_learning_starts_and_every_n_episodes_are_kept() -> None:
    env = vec_env(2)
    settings = PER_EPISODE | {"train_freq": [2, "episode"], "learning_starts": 100}
    model = make_model("sac", env, seed=97, overrides=settings)
    (training,) = training_callbacks("sac", settings, env.num_envs)
    ended_after_start = []

    class CountAfterStart(EpisodicTraining):  # the same counting, kept apart from the one under test
        def _on_rollout_end(self) -> None:
            if self.num_timesteps > self.model.learning_starts:
                ended_after_start.append(self.ended)
            self.ended = 0

    model.learn(300, callback=[training, CountAfterStart(training.schedule)])
    assert training.gradient_steps_taken == 3 * (sum(ended_after_start) // 2)
    assert training.gradient_steps_taken > 0
    env.close()


def test_gradient_steps_minus_one_is_refused_on_several_envs() -> None:
    with pytest.raises(ValueError, match="gradient_steps -1"):
        episodic_schedule(PER_EPISODE | {"gradient_steps": -1}, 2)


def test_a_model_saved_on_one_env_resumes_per_episode_on_several(tmp_path) -> None:
    one = vec_env(1)
    make_model("sac", one, seed=97, overrides=PER_EPISODE).save(tmp_path / "model.zip")
    one.close()
    env = vec_env(3)
    model = load_for_resume("sac", tmp_path / "model.zip", env, device="cpu", overrides=PER_EPISODE)
    assert (model.train_freq.frequency, model.gradient_steps) == (64, 0)
    callbacks = training_callbacks("sac", PER_EPISODE, env.num_envs)
    model.learn(200, callback=callbacks)
    assert callbacks[0].gradient_steps_taken == 3 * len(model.ep_info_buffer) > 0
    env.close()


def test_rollouts_keep_gsde_noise_for_sde_sample_freq_steps_and_are_one_step_without_it() -> None:
    assert vectorised_kwargs(PER_EPISODE | {"use_sde": True, "sde_sample_freq": 16}, 4)["train_freq"] == (16, "step")
    assert vectorised_kwargs(PER_EPISODE | {"use_sde": False}, 4)["train_freq"] == (1, "step")
    assert vectorised_kwargs(PER_EPISODE | {"use_sde": True, "sde_sample_freq": -1}, 4)["train_freq"] == (1, "step")
