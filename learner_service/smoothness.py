"""Smooth actions by regularising the actor (CAPS, Mysore et al., ICRA 2021).

A policy whose action jumps between nearly equal observations makes the rover twitch: the SPEC's smoothness
metrics S_D and S_A count those jumps, and SAC trained from scratch here scores several times the paper's. CAPS adds
two terms to every actor update, each on a minibatch from the replay buffer, and a third keeps the action in range:

- temporal: ``temporal`` x the mean squared difference of the deterministic actions at consecutive observations
  (s, s'), so the action changes no faster than the observation does;
- spatial: ``spatial`` x the mean squared difference between the action at s and at s plus Gaussian noise of std
  ``sigma``, so nearby observations map to nearby actions;
- bound: ``bound`` x the mean squared excess of the deterministic action beyond where the actor can still move
  it. An on-policy Gaussian's mean is unbounded and the env clips it, so PPO can learn a bang-bang controller that
  alternates the clipped extremes every step (its actions' means reached 122 here), which the two CAPS terms
  cannot tame at a weight PPO's small loss survives; kept inside the bounds, the mean's steps are at most the
  action range. A squashed actor (SAC, TD3) never leaves the bounds but can saturate: its tanh's input grows until
  the slope, and with it every gradient the critic sends, is gone (a TD3 seed here held full surge into the
  dolphin for 80k steps, its pre-squash surge about 8 on average). For it the excess is that input's beyond
  ``SATURATION``, where tanh reaches 0.99 of the range, so nothing inside 99% of the range is penalised.

No term touches the reward or the critic. The learner's own ``train`` stays untouched: like the kept cloning
loss (``learner_service.demonstrations.keep_cloning``), a hook on the actor's optimizer adds the terms' gradient to
the one the learner's loss left, just before each step.

An off-policy learner's minibatches come from its replay buffer. An on-policy one (PPO) has the current rollout
instead: its pairs are consecutive steps of one env that no episode start separates, and the hook sits on the
policy's optimizer (one network for actor and value), so every minibatch step of every epoch adds the terms.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from learner_service.learn_settings import SmoothSettings
from learner_service.registry import deterministic_action


def smoothness_loss(policy: Any, observations: torch.Tensor, next_observations: torch.Tensor,
                    settings: SmoothSettings, generator: torch.Generator) -> torch.Tensor:  # fmt: skip
    """The weighted CAPS terms on one minibatch of observations and their successors."""
    actions = deterministic_action(policy, observations)
    loss = actions.new_zeros(())
    if settings.temporal > 0:
        following = deterministic_action(policy, next_observations)
        loss = loss + settings.temporal * (actions - following).pow(2).sum(dim=1).mean()
    if settings.spatial > 0:
        noise = torch.randn(observations.shape, generator=generator, device=observations.device) * settings.sigma
        nearby = deterministic_action(policy, observations + noise)
        loss = loss + settings.spatial * (actions - nearby).pow(2).sum(dim=1).mean()
    if settings.bound > 0:
        loss = loss + settings.bound * action_excess(policy, observations, actions).pow(2).sum(dim=1).mean()
    return loss


#: tanh's input beyond which it is within 1% of its bound (and its slope under 2%): a squashed actor saturates there.
SATURATION = float(np.arctanh(0.99))


def presquash_action(policy: Any, observations: torch.Tensor) -> torch.Tensor | None:
    """A squashed actor's deterministic action before its tanh (SAC's mean, TD3's and DDPG's last layer); None for
    an actor that does not squash."""
    actor = getattr(policy, "actor", None)
    if actor is None:
        return None
    if hasattr(actor, "get_action_dist_params"):  # SAC: the squashed Gaussian's mean (gSDE clips it at 2 already)
        return actor.get_action_dist_params(observations)[0]
    head = getattr(actor, "mu", None)
    if isinstance(head, nn.Sequential) and isinstance(head[-1], nn.Tanh):  # TD3, DDPG: a network ending in tanh
        return head[:-1](actor.extract_features(observations, actor.features_extractor))
    return None


def action_excess(policy: Any, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The bound term's excess of each action: beyond the action space for an unsquashed actor, beyond
    ``SATURATION`` before the squash for a squashed one (0 where the actor can still move the action)."""
    presquash = presquash_action(policy, observations)
    if presquash is None:
        return bound_excess(actions, policy.action_space)
    return torch.relu(presquash.abs() - SATURATION)


def bound_excess(actions: torch.Tensor, action_space: spaces.Box) -> torch.Tensor:
    """How far each action lies beyond the action space's box (0 inside it)."""
    low = torch.as_tensor(action_space.low, dtype=actions.dtype, device=actions.device)
    high = torch.as_tensor(action_space.high, dtype=actions.dtype, device=actions.device)
    return torch.relu(actions - high) + torch.relu(low - actions)


Pairs = Callable[[int], tuple[torch.Tensor, torch.Tensor]]  # batch size -> (observations, their successors)


def replay_pairs(model: Any) -> Pairs:
    """Minibatches of (s, s') from an off-policy learner's replay buffer."""

    def sample(batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        batch = model.replay_buffer.sample(batch_size)
        return batch.observations, batch.next_observations

    return sample


def rollout_pairs(model: Any, seed: int) -> Pairs:
    """Minibatches of (s, s') from an on-policy learner's current rollout: step t and t + 1 of one env where no
    episode starts at t + 1."""
    rng = np.random.default_rng(seed)

    def sample(batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        buffer = model.rollout_buffer
        steps, envs = buffer.buffer_size, buffer.n_envs
        observations = buffer.observations
        if observations.ndim == 2:  # flattened env-major for training (RolloutBuffer.swap_and_flatten): to (t, env)
            observations = observations.reshape(envs, steps, -1).swapaxes(0, 1)
        continuing = np.argwhere(buffer.episode_starts[1:] == 0)  # (t, env) whose next step is the same episode's
        if len(continuing) == 0:
            raise ValueError("the rollout has no two consecutive steps of one episode; lengthen n_steps")
        step, env = continuing[rng.integers(len(continuing), size=batch_size)].T
        return buffer.to_torch(observations[step, env]), buffer.to_torch(observations[step + 1, env])

    return sample


def keep_smooth(model: Any, settings: SmoothSettings, seed: int) -> Any:
    """Add the CAPS terms to every actor update of ``model`` from now on; returns the hook's handle.

    Refused, naming why, for a learner with neither an actor and a replay buffer (SAC, TD3) nor a policy and a
    rollout buffer (PPO, A2C), or, for the spatial term, an observation that is not one flat vector (image
    observations).
    """
    if hasattr(model, "actor") and hasattr(model, "replay_buffer"):
        pairs, optimizer = replay_pairs(model), model.actor.optimizer
    elif hasattr(model, "rollout_buffer") and hasattr(model.policy, "optimizer"):
        pairs, optimizer = rollout_pairs(model, seed), model.policy.optimizer
    else:
        raise ValueError(f"--smooth-* needs an actor and a replay buffer or a policy and a rollout buffer; "
                         f"{type(model).__name__} has neither")  # fmt: skip
    if settings.spatial > 0 and not isinstance(model.observation_space, spaces.Box):
        raise ValueError("--smooth-spatial perturbs one flat observation vector; use cmvae or state observations")
    generator = torch.Generator(device=model.device).manual_seed(seed)

    def add_smoothness_gradient(optimizer: torch.optim.Optimizer, args: Any, kwargs: Any) -> None:
        observations, next_observations = pairs(settings.batch_size)
        smoothness_loss(model.policy, observations, next_observations, settings, generator).backward()

    return optimizer.register_step_pre_hook(add_smoothness_gradient)
