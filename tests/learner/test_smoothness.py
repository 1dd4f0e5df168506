"""CAPS smoothness terms on real stable-baselines3 learners (Pendulum: a small Box env that needs no rendering)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO, SAC, TD3
from stable_baselines3.common.env_util import make_vec_env

from learner_service.learn_settings import SmoothSettings
from learner_service.registry import deterministic_action
from learner_service.smoothness import (
    SATURATION,
    bound_excess,
    keep_smooth,
    presquash_action,
    rollout_pairs,
    smoothness_loss,
)


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


def _ppo(seed: int = 0, learning_rate: float = 3e-4) -> PPO:
    return PPO("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=seed), n_steps=128, batch_size=64, n_epochs=4,
               learning_rate=learning_rate, seed=seed, policy_kwargs={"net_arch": [32, 32]})  # fmt: skip


def _rollout_action_change(model: PPO) -> float:
    """Mean squared change of the deterministic action between consecutive steps of the last rollout's envs."""
    buffer = model.rollout_buffer
    observations = buffer.observations.reshape(buffer.n_envs, buffer.buffer_size, -1)  # flattened env-major
    with torch.no_grad():
        actions = deterministic_action(model.policy, buffer.to_torch(observations.reshape(-1, observations.shape[-1])))
    actions = actions.reshape(buffer.n_envs, buffer.buffer_size, -1)
    return float((actions[:, 1:] - actions[:, :-1]).pow(2).sum(dim=2).mean())


def test_an_on_policy_learner_smooths_from_its_rollout() -> None:
    plain, smooth = _ppo(), _ppo()
    keep_smooth(smooth, SmoothSettings(temporal=50.0, spatial=1.0), seed=0)
    for model in (plain, smooth):
        model.learn(1024)
    assert _rollout_action_change(smooth) < 0.5 * _rollout_action_change(plain)


def _pushed_out_ppo() -> PPO:
    """A PPO on Pendulum (actions in [-2, 2]) whose deterministic actions all start at 3, outside the bounds; its
    learning rate lets a few hundred steps move them back."""
    model = _ppo(learning_rate=0.05)
    with torch.no_grad():
        model.policy.action_net.weight.zero_()
        model.policy.action_net.bias.fill_(3.0)
    return model


def _largest_excess(model: PPO) -> float:
    observations = torch.as_tensor(model.rollout_buffer.observations.reshape(-1, 3))
    with torch.no_grad():
        return float(bound_excess(deterministic_action(model.policy, observations), model.action_space).max())


def _saturated_td3() -> TD3:
    """A TD3 on Pendulum whose actor's tanh starts saturated: its input is 8 for every observation, where tanh's
    slope (4.5e-7) leaves no gradient for the critic to turn it with; its learning rate lets a few hundred actor
    updates move it."""
    model = TD3("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=100, batch_size=64, learning_rate=0.05,
                seed=0, policy_kwargs={"net_arch": [32, 32]})  # fmt: skip
    last_layer = model.actor.mu[-2]
    with torch.no_grad():
        last_layer.weight.zero_()
        last_layer.bias.fill_(8.0)
    return model


def _largest_presquash(model: TD3) -> float:
    batch = model.replay_buffer.sample(512)
    with torch.no_grad():
        return float(presquash_action(model.policy, batch.observations).abs().max())


def test_the_bound_term_is_the_squared_excess_beyond_the_box_or_beyond_the_squash_saturating() -> None:
    observations = torch.as_tensor(np.random.default_rng(0).normal(size=(8, 3)), dtype=torch.float32)
    generator = torch.Generator().manual_seed(0)
    bound = SmoothSettings(bound=2.0)
    assert smoothness_loss(_pushed_out_ppo().policy, observations, observations, bound, generator).item() == \
        pytest.approx(2.0 * 1.0**2)  # fmt: skip
    assert smoothness_loss(_sac().policy, observations, observations, bound, generator).item() == 0.0  # unsaturated
    assert smoothness_loss(_saturated_td3().policy, observations, observations, bound, generator).item() == \
        pytest.approx(2.0 * (8.0 - SATURATION) ** 2, rel=1e-5)  # fmt: skip
    assert presquash_action(_ppo().policy, observations) is None  # PPO's Gaussian does not squash


def test_the_bound_term_brings_a_saturated_squashed_actor_back_where_its_gradient_lives() -> None:
    plain, bounded = _saturated_td3(), _saturated_td3()
    keep_smooth(bounded, SmoothSettings(bound=1.0), seed=0)
    for model in (plain, bounded):
        model.learn(600)
    assert _largest_presquash(plain) > 7.5  # without the term nothing moves it
    assert _largest_presquash(bounded) < SATURATION + 0.5, _largest_presquash(bounded)


def test_the_bound_term_brings_an_on_policy_mean_back_inside_the_action_space() -> None:
    plain, bounded = _pushed_out_ppo(), _pushed_out_ppo()
    keep_smooth(bounded, SmoothSettings(bound=1.0), seed=0)
    for model in (plain, bounded):
        model.learn(1024)
    assert _largest_excess(bounded) < 0.2 * _largest_excess(plain), (_largest_excess(bounded), _largest_excess(plain))


def test_a_rollout_with_no_consecutive_steps_of_one_episode_is_named() -> None:
    model = _ppo()
    model.learn(256)
    model.rollout_buffer.episode_starts[:] = 1.0  # every step starts an episode: no (s, s') pair exists
    with pytest.raises(ValueError, match="no two consecutive steps of one episode"):
        rollout_pairs(model, seed=0)(8)


def test_a_learner_without_a_buffer_is_refused_by_name() -> None:
    class Planner:
        policy = None

    with pytest.raises(ValueError, match="Planner has neither"):
        keep_smooth(Planner(), SmoothSettings(temporal=1.0), seed=0)


def test_bad_smoothness_settings_are_refused() -> None:
    for bad in (SmoothSettings(temporal=-1.0), SmoothSettings(sigma=0.0), SmoothSettings(batch_size=0),
                SmoothSettings(bound=-0.5)):  # fmt: skip
        with pytest.raises(ValueError, match="--smooth-"):
            bad.check()
    assert not SmoothSettings().enabled and SmoothSettings(spatial=0.1).enabled and SmoothSettings(bound=1).enabled


def test_swimm_learn_accepts_smoothing_for_off_and_on_policy_learners() -> None:
    from learner_service.command import check
    from learner_service.learn_settings import LearnCommandSettings

    for algo in ("sac", "td3", "ppo"):
        check(LearnCommandSettings(algo=algo, smooth=SmoothSettings(temporal=1.0)))
