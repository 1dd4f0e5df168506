"""Saving a run's model with its replay buffer, and resuming training from a saved model.

A checkpoint is SB3's zip; an off-policy learner's replay buffer lies beside it as a pickle named after it
(``model_5000_steps.zip`` -> ``model_replay_buffer_5000_steps.pkl``, as SB3's CheckpointCallback names it;
``final_model.zip`` -> ``final_model_replay_buffer.pkl``). Resuming loads both when both exist, so SAC goes on
learning from the transitions it had, not from an empty buffer; without the buffer it warns and goes on.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

from learner_service.episodic import schedule_objects
from learner_service.registry import merge_overrides, resolve_algorithm

log = logging.getLogger(__name__)

_STEPS_NAME = re.compile(r"(?P<prefix>.*)_(?P<steps>\d+)_steps")


def replay_buffer_path(model_path: str | Path) -> Path:
    """Where the replay buffer saved with ``model_path`` lies (see the module docstring)."""
    path = Path(model_path)
    name = path.name.removesuffix(".zip")
    match = _STEPS_NAME.fullmatch(name)
    if match:
        return path.with_name(f"{match['prefix']}_replay_buffer_{match['steps']}_steps.pkl")
    return path.with_name(f"{name}_replay_buffer.pkl")


def has_replay_buffer(model: Any) -> bool:
    return getattr(model, "replay_buffer", None) is not None and callable(getattr(model, "save_replay_buffer", None))


def save_model(model: Any, path: str | Path, replay_buffer: bool = True) -> Path:
    """Save ``model`` (and its replay buffer, if it has one and ``replay_buffer``); returns the zip's path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    if replay_buffer and has_replay_buffer(model):
        model.save_replay_buffer(replay_buffer_path(path))
    log.info("saved the model at %d steps to %s", model.num_timesteps, path)
    return path


def load_for_resume(
    algo: str, path: str | Path, env: Any, device: str = "auto", overrides: dict[str, Any] | None = None, **kwargs: Any
) -> Any:
    """A saved model of ``algo`` on ``env``, with its replay buffer if one lies beside it, ready to learn on.

    It trains by the schedule a new model of ``algo`` with ``overrides`` would (``train_freq``, ``gradient_steps``,
    on ``env``'s number of envs: learner_service/episodic.py), so pass ``learn()`` the same
    :func:`learner_service.registry.training_callbacks`. ``kwargs`` set model attributes at load (e.g.
    ``tensorboard_log``). Train it on with ``learn(..., reset_num_timesteps=False)`` so its step count (and
    schedules) continue.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"cannot resume: {path} does not exist")
    cls, defaults = resolve_algorithm(algo)
    schedule = schedule_objects(merge_overrides(defaults, overrides), getattr(env, "num_envs", 1))
    model = cls.load(path, env=env, device=device, custom_objects=schedule, **kwargs)
    buffer = replay_buffer_path(path)
    if has_replay_buffer(model):
        if buffer.is_file():
            model.load_replay_buffer(buffer)
            log.info(
                "resumed %s at %d steps with %d transitions from %s",
                path,
                model.num_timesteps,
                model.replay_buffer.size(),
                buffer,
            )
        else:
            log.warning("resuming %s at %d steps with an empty replay buffer: no %s", path, model.num_timesteps, buffer)
    else:
        log.info("resumed %s at %d steps", path, model.num_timesteps)
    return model
