"""Smooth actions by regularising the actor (CAPS, Mysore et al., ICRA 2021), for off-policy learners.

A policy whose action jumps between nearly equal observations makes the rover twitch: the SPEC's smoothness
metrics S_D and S_A count those jumps, and SAC trained from scratch here scores several times the paper's. CAPS adds
two terms to every actor update, each on a minibatch from the replay buffer:

- temporal: ``temporal`` x the mean squared difference of the deterministic actions at consecutive observations
  (s, s'), so the action changes no faster than the observation does;
- spatial: ``spatial`` x the mean squared difference between the action at s and at s plus Gaussian noise of std
  ``sigma``, so nearby observations map to nearby actions.

Neither term touches the reward or the critic. The learner's own ``train`` stays untouched: like the kept cloning
loss (``learner_service.demonstrations.keep_cloning``), a hook on the actor's optimizer adds the terms' gradient to
the one the learner's loss left, just before each step.
"""

from __future__ import annotations

from typing import Any

import torch
from gymnasium import spaces

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
    return loss


def keep_smooth(model: Any, settings: SmoothSettings, seed: int) -> Any:
    """Add the CAPS terms to every actor update of an off-policy ``model`` from now on; returns the hook's handle.

    Refused, naming why, for a learner without an actor and a replay buffer (PPO) or, for the spatial term, an
    observation that is not one flat vector (image observations).
    """
    if not (hasattr(model, "actor") and hasattr(model, "replay_buffer")):
        raise ValueError(f"--smooth-* needs an off-policy learner with an actor and a replay buffer; "
                         f"{type(model).__name__} has none")  # fmt: skip
    if settings.spatial > 0 and not isinstance(model.observation_space, spaces.Box):
        raise ValueError("--smooth-spatial perturbs one flat observation vector; use cmvae or state observations")
    generator = torch.Generator(device=model.device).manual_seed(seed)

    def add_smoothness_gradient(optimizer: torch.optim.Optimizer, args: Any, kwargs: Any) -> None:
        batch = model.replay_buffer.sample(settings.batch_size)
        smoothness_loss(model.policy, batch.observations, batch.next_observations, settings, generator).backward()

    return model.actor.optimizer.register_step_pre_hook(add_smoothness_gradient)
