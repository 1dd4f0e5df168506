"""CAPS smoothness terms on real stable-baselines3 learners (Pendulum: a small Box env that needs no rendering)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO, SAC

from learner_service.learn_settings import SmoothSettings
from learner_service.registry import deterministic_action
from learner_service.smoothness import keep_smooth, smoothness_loss


def _sac(seed: int = 0) -> SAC:
    return SAC("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=100, batch_size=64, seed=seed,
               policy_kwargs={"net_arch": [32, 32]})  # fmt: skip


def _action_change(model: SAC, rows: int = 512) -> float:
    """Mean squared change of the deterministic action between consecutive buffered observations."""
    batch = model.replay_buffer.sample(rows)
    with torch.no_grad():
        now = deterministic_action(model.policy, batch.observations)
        following = deterministic_action(model.policy, batch.next_observations)
    return float((now - following).pow(2).sum(dim=1).mean())


def test_the_temporal_term_makes_consecutive_actions_closer_than_training_without_it() -> None:
    plain, smooth = _sac(), _sac()
    keep_smooth(smooth, SmoothSettings(temporal=50.0), seed=0)
    for model in (plain, smooth):
        model.learn(300)
    assert _action_change(smooth) < 0.5 * _action_change(plain), (_action_change(smooth), _action_change(plain))


def test_the_loss_is_zero_for_equal_observations_and_weighs_each_term() -> None:
    model = _sac()
    observations = torch.as_tensor(np.random.default_rng(0).normal(size=(8, 3)), dtype=torch.float32)
    generator = torch.Generator().manual_seed(0)
    same = smoothness_loss(model.policy, observations, observations, SmoothSettings(temporal=1.0), generator)
    assert same.item() == 0.0
    shifted = observations + 1.0
    once = smoothness_loss(model.policy, observations, shifted, SmoothSettings(temporal=1.0), generator)
    twice = smoothness_loss(model.policy, observations, shifted, SmoothSettings(temporal=2.0), generator)
    assert once.item() > 0 and twice.item() == pytest.approx(2 * once.item())
    spatial = smoothness_loss(model.policy, observations, observations, SmoothSettings(spatial=1.0), generator)
    assert spatial.item() > 0  # the noisy neighbours' actions differ


def test_an_on_policy_learner_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="off-policy.*PPO"):
        keep_smooth(PPO("MlpPolicy", gym.make("Pendulum-v1")), SmoothSettings(temporal=1.0), seed=0)


def test_bad_smoothness_settings_are_refused() -> None:
    for bad in (SmoothSettings(temporal=-1.0), SmoothSettings(sigma=0.0), SmoothSettings(batch_size=0)):
        with pytest.raises(ValueError, match="smooth"):
            bad.check()
    assert not SmoothSettings().enabled and SmoothSettings(spatial=0.1).enabled


def test_swimm_learn_refuses_smoothing_an_on_policy_learner_before_anything_starts() -> None:
    from learner_service.command import check
    from learner_service.learn_settings import LearnCommandSettings

    with pytest.raises(ValueError, match="off-policy.*ppo"):
        check(LearnCommandSettings(algo="ppo", smooth=SmoothSettings(temporal=1.0)))
    check(LearnCommandSettings(algo="sac", smooth=SmoothSettings(temporal=1.0)))  # accepted
