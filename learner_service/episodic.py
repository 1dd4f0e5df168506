"""Per-episode training with several envs: the SPEC's update-to-data ratio whatever the number of envs.

The SPEC's SAC takes 64 gradient steps after every episode (``train_freq: [1, episode]``), which stable-baselines3
allows with one env only ("You must use only one env when doing episodic training"). With N envs, episodes end at
different steps, so here the model collects rollouts of a fixed number of vector steps and trains nothing itself
(``gradient_steps: 0``, SB3's "no training" case), and :class:`EpisodicTraining` takes ``gradient_steps`` for each
episode that ended, at the end of the rollout it ended in. One env or eight, a finished episode buys the same
number of gradient steps: the same updates per env step as the SPEC's single-env run on the same episodes.

A rollout is ``sde_sample_freq`` vector steps when the policy explores with gSDE (SB3 draws new exploration noise
at the start of every rollout, so rollouts of one step would redraw it every step instead of every
``sde_sample_freq``), else one vector step, so training follows an episode's end at once.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EpisodicSchedule:
    episodes: int  # train after every this many finished episodes
    gradient_steps: int  # per training, as SB3's gradient_steps


def episodic_schedule(kwargs: Mapping[str, Any], n_envs: int) -> EpisodicSchedule | None:
    """The schedule to run by :class:`EpisodicTraining` when ``kwargs`` train per episode and there are several
    envs; None when SB3 can run ``kwargs`` as they are."""
    train_freq = kwargs.get("train_freq")
    if n_envs < 2 or train_freq is None:
        return None
    episodes, unit = frequency_and_unit(train_freq)
    if unit != "episode":
        return None
    gradient_steps = int(kwargs.get("gradient_steps", 1))
    if gradient_steps < 0:
        raise ValueError(
            "gradient_steps -1 (as many as the rollout's steps) has no per-episode meaning with several envs; "
            "give a number of gradient steps per episode"
        )
    return EpisodicSchedule(episodes, gradient_steps)


def vectorised_kwargs(kwargs: Mapping[str, Any], n_envs: int) -> dict[str, Any]:
    """``kwargs`` for SB3 with ``n_envs`` envs, keeping the gradient steps per env step: a per-episode schedule
    becomes rollouts with no training of SB3's own (:class:`EpisodicTraining` does it), and ``train_freq: [N,
    step]``, which SB3 counts in vector steps of ``n_envs`` env steps each, is converted to count env steps
    (:func:`per_env_steps`); anything else is returned unchanged."""
    schedule = episodic_schedule(kwargs, n_envs)
    if schedule is None:
        return per_env_steps(kwargs, n_envs)
    log.info(
        "%d envs: %d gradient step(s) after every %d finished episode(s), taken by EpisodicTraining at the end of "
        "rollouts of %d vector step(s)",
        n_envs,
        schedule.gradient_steps,
        schedule.episodes,
        rollout_steps(kwargs),
    )
    return {**kwargs, "train_freq": (rollout_steps(kwargs), "step"), "gradient_steps": 0}


def per_env_steps(kwargs: Mapping[str, Any], n_envs: int) -> dict[str, Any]:
    """``train_freq: [N, step]`` in env steps on ``n_envs`` envs: every round(N / n_envs) vector steps (at least
    one), with the gradient steps scaled by the env steps that really are between two trainings, so the update-to-
    data ratio stays what N and ``gradient_steps`` say."""
    train_freq, gradient_steps = kwargs.get("train_freq"), kwargs.get("gradient_steps")
    if n_envs < 2 or train_freq is None or not isinstance(gradient_steps, int) or gradient_steps < 0:
        return dict(kwargs)
    frequency, unit = frequency_and_unit(train_freq)
    if unit != "step":
        return dict(kwargs)
    vector_steps = max(1, round(frequency / n_envs))
    scaled = max(1, round(gradient_steps * vector_steps * n_envs / frequency)) if gradient_steps else 0
    log.info(
        "%d envs: train_freq %d env steps is every %d vector steps (%d env steps), %d gradient step(s) each",
        n_envs,
        frequency,
        vector_steps,
        vector_steps * n_envs,
        scaled,
    )
    return {**kwargs, "train_freq": (vector_steps, "step"), "gradient_steps": scaled}


def frequency_and_unit(train_freq: Any) -> tuple[int, str]:
    """(N, "step" or "episode") of a ``train_freq`` as the YAML or SB3 writes it: N, [N, unit] or (N, unit)."""
    if isinstance(train_freq, list | tuple):
        return int(train_freq[0]), str(train_freq[-1]).removesuffix("s")
    return int(train_freq), "step"


def rollout_steps(kwargs: Mapping[str, Any]) -> int:
    """Vector steps per rollout under :class:`EpisodicTraining` (see the module docstring)."""
    sde_sample_freq = int(kwargs.get("sde_sample_freq", -1))
    return sde_sample_freq if kwargs.get("use_sde") and sde_sample_freq > 0 else 1


class EpisodicTraining(BaseCallback):
    """Takes ``schedule.gradient_steps`` for every ``schedule.episodes`` episodes that ended, once the model is past
    its ``learning_starts`` (episodes that end before then buy nothing, as in SB3's own loop)."""

    def __init__(self, schedule: EpisodicSchedule) -> None:
        super().__init__()
        self.schedule = schedule
        self.ended = 0  # finished episodes not yet trained on
        self.gradient_steps_taken = 0

    def _on_step(self) -> bool:
        self.ended += int(np.count_nonzero(self.locals["dones"]))
        return True

    def _on_rollout_end(self) -> None:
        """After SB3 has stored the rollout's transitions, so the episodes' last steps are in the buffer."""
        if self.num_timesteps <= self.model.learning_starts:
            self.ended = 0
            return
        updates, self.ended = divmod(self.ended, self.schedule.episodes)
        if updates:
            steps = updates * self.schedule.gradient_steps
            self.model.train(gradient_steps=steps, batch_size=self.model.batch_size)
            self.gradient_steps_taken += steps


def episodic_callbacks(kwargs: Mapping[str, Any], n_envs: int) -> list[BaseCallback]:
    """The callback a model built with :func:`vectorised_kwargs` needs to train, or none."""
    schedule = episodic_schedule(kwargs, n_envs)
    return [] if schedule is None else [EpisodicTraining(schedule)]


def schedule_objects(kwargs: Mapping[str, Any], n_envs: int) -> dict[str, Any]:
    """``custom_objects`` for SB3's ``load``: the training schedule of ``kwargs`` on ``n_envs`` envs, in place of the
    one the model was saved with (SB3 keeps a saved model's own otherwise)."""
    vectorised = vectorised_kwargs(kwargs, n_envs)
    if "train_freq" not in vectorised:
        return {}
    frequency, unit = frequency_and_unit(vectorised["train_freq"])
    objects = {"train_freq": TrainFreq(frequency, TrainFrequencyUnit(unit))}
    if "gradient_steps" in vectorised:
        objects["gradient_steps"] = int(vectorised["gradient_steps"])
    return objects
