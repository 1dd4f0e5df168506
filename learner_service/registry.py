"""The learner registry: algorithms by name or by import path, with their tuned defaults, and policies to evaluate.

A named algorithm is a YAML file in ``hyperparams/`` (``algorithm: package.module:Class`` plus the model's
keyword arguments), so SAC, PPO and TD3 are data, not code. Any other class that follows the
stable-baselines3 API (``Class(policy, env, seed=..., **kwargs)``, ``learn``, ``predict``, ``Class.load``)
is reachable as ``"package.module:Class"``: adding a learner needs a YAML file or an import path, never a
change to the services.

YAML values that cannot be plain data are written as names and resolved here:
``"lin_<x>"`` is a schedule falling linearly from x to 0 over training; ``policy_kwargs.activation_fn``
names a ``torch.nn`` class; ``action_noise: {type: ornstein_uhlenbeck | normal | pink, sigma: s}`` becomes an
SB3 noise object sized to the env's action space (``sigma`` one scale, or a list of one per action dimension;
pink: one seeded process per env, ``seq_len`` steps long); a
``train_freq`` list becomes SB3's (n, unit) tuple.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch
import yaml
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import (
    ActionNoise,
    NormalActionNoise,
    OrnsteinUhlenbeckActionNoise,
    VectorizedActionNoise,
)
from stable_baselines3.common.utils import LinearSchedule

from encoder_service import DEFAULT_CHECKPOINT
from encoder_service.inference import open_encoder
from learner_service.episodic import episodic_callbacks, vectorised_kwargs
from learner_service.identity import check_task, read_identity
from learner_service.learn_settings import TrackerGains
from learner_service.scripted import LatentTracker, ScriptedTracker

log = logging.getLogger(__name__)

HYPERPARAMS_DIR = Path(__file__).parent / "hyperparams"
SCRIPTED = "scripted"
LATENT_SCRIPTED = "scripted-camera"  # the scripted tracker on the CMVAE's decoded d, theta (and elevation)
SCRIPTED_NAMES = (SCRIPTED, LATENT_SCRIPTED)
LINEAR_SCHEDULE_PREFIX = "lin_"
ACTION_NOISES = {"ornstein_uhlenbeck": OrnsteinUhlenbeckActionNoise, "normal": NormalActionNoise}
PINK_NOISE = "pink"  # colored noise with a 1/f spectrum (pink-noise-rl), built per env from the model's seed
PINK_SEQ_LEN = 3000  # its default period: the SPEC's episode length
SB3_API = ("learn", "predict", "load")


@runtime_checkable
class Policy(Protocol):
    """What the evaluator drives: one deterministic action per observation (``info`` for ground-truth baselines)."""

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray: ...


class SB3Policy:
    """A trained SB3-API model acting deterministically."""

    def __init__(self, model: Any) -> None:
        self.model = model

    def act(self, obs: Any, info: dict[str, Any]) -> np.ndarray:
        action, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(action, dtype=np.float32)


def deterministic_action(policy: Any, obs: torch.Tensor) -> torch.Tensor:
    """A stable-baselines3 policy's deterministic action as a differentiable tensor, before ``predict``'s scaling and
    clipping: its ``forward`` (off-policy policies return the action, on-policy ones (action, value, log-prob))."""
    actions = policy(obs, deterministic=True)
    return actions[0] if isinstance(actions, tuple) else actions


def algorithm_names() -> list[str]:
    """Every algorithm known by name: the YAML files' stems and the scripted baseline."""
    return sorted([path.stem for path in HYPERPARAMS_DIR.glob("*.yaml")] + list(SCRIPTED_NAMES))


def load_hyperparams(algo: str) -> dict[str, Any]:
    """The YAML of a named algorithm: ``algorithm`` (import path), ``n_timesteps``, ``model`` (keyword arguments)."""
    path = HYPERPARAMS_DIR / f"{algo}.yaml"
    if not path.is_file():
        raise ValueError(f"no hyperparameters for {algo!r}; named algorithms: {', '.join(algorithm_names())}")
    with path.open() as handle:
        params = yaml.safe_load(handle)
    if not isinstance(params, dict) or "algorithm" not in params:
        raise ValueError(f"{path} must be a mapping with an 'algorithm: package.module:Class' entry")
    return params


def import_algorithm(path: str) -> type:
    """The class at ``"package.module:Class"``, checked for the SB3 API; ValueError says what is wrong."""
    module_name, _, class_name = path.partition(":")
    if not module_name or not class_name:
        raise ValueError(f"{path!r} is not an import path; write it as 'package.module:Class'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"cannot import module {module_name!r} for algorithm {path!r}: {exc}") from exc
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type):
        raise ValueError(f"module {module_name!r} has no class {class_name!r}")
    missing = [name for name in SB3_API if not callable(getattr(cls, name, None))]
    if missing:
        raise ValueError(f"{path} does not follow the stable-baselines3 API: it lacks {', '.join(missing)}")
    return cls


def resolve_algorithm(algo: str) -> tuple[type, dict[str, Any]]:
    """The class and default model keyword arguments of a name ("sac") or an import path ("pkg.mod:Class")."""
    if ":" in algo:
        return import_algorithm(algo), {}
    if algo in SCRIPTED_NAMES:
        raise ValueError(f"the scripted baseline has nothing to train; use load_policy({algo!r}, None)")
    if algo not in algorithm_names():
        raise ValueError(
            f"unknown algorithm {algo!r}; choose one of {', '.join(algorithm_names())} or give 'package.module:Class'"
        )
    params = load_hyperparams(algo)
    return import_algorithm(params["algorithm"]), dict(params.get("model") or {})


def merge_overrides(defaults: Mapping[str, Any], overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """Overrides on top of defaults; ``policy_kwargs`` merge key by key so one can change a single entry."""
    merged = dict(defaults)
    for key, value in (overrides or {}).items():
        if key == "policy_kwargs" and isinstance(value, Mapping):
            merged[key] = {**(merged.get(key) or {}), **value}
        else:
            merged[key] = value
    return merged


def resolve_kwargs(
    kwargs: Mapping[str, Any], action_space: gym.spaces.Space, n_envs: int = 1, seed: int | None = None
) -> dict[str, Any]:
    """Turn the YAML's names into objects: schedules, action noise (for ``n_envs`` envs, seeded by ``seed``),
    train_freq tuples, activation classes."""
    resolved: dict[str, Any] = {}
    for key, value in kwargs.items():
        if isinstance(value, str) and value.startswith(LINEAR_SCHEDULE_PREFIX):
            resolved[key] = linear_schedule(value)
        elif key == "action_noise" and isinstance(value, Mapping):
            resolved[key] = action_noise(value, action_space, n_envs, seed)
        elif key == "train_freq" and isinstance(value, list):
            resolved[key] = tuple(value)
        elif key == "policy_kwargs" and isinstance(value, Mapping):
            resolved[key] = resolve_policy_kwargs(value)
        else:
            resolved[key] = value
    return resolved


def linear_schedule(spec: str) -> LinearSchedule:
    """``"lin_<x>"``: x at the start of training, falling linearly to 0 at its end."""
    try:
        start = float(spec[len(LINEAR_SCHEDULE_PREFIX) :])
    except ValueError as exc:
        raise ValueError(f"bad schedule {spec!r}; write 'lin_<number>', e.g. 'lin_1e-4'") from exc
    return LinearSchedule(start, 0.0, 1.0)


def action_noise(
    spec: Mapping[str, Any], action_space: gym.spaces.Space, n_envs: int = 1, seed: int | None = None
) -> ActionNoise:
    kind = spec.get("type")
    size = int(np.prod(action_space.shape))
    sigma = noise_scales(spec.get("sigma", 0.1), size)
    if kind == PINK_NOISE:
        return pink_noise(sigma, int(spec.get("seq_len", PINK_SEQ_LEN)), size, n_envs, seed)
    if kind not in ACTION_NOISES:
        raise ValueError(f"unknown action noise {kind!r}; choose one of {', '.join([*ACTION_NOISES, PINK_NOISE])}")
    return ACTION_NOISES[kind](mean=np.zeros(size), sigma=sigma)


def noise_scales(sigma: Any, size: int) -> np.ndarray:
    """An action noise's ``sigma``, one number for every action dimension or a list of one each (a tracker may
    want its surge explored further than its yaw), as ``size`` non-negative scales."""
    try:
        scales = np.broadcast_to(np.asarray(sigma, dtype=float), (size,)).copy()
    except (TypeError, ValueError):
        raise ValueError(f"action noise sigma must be a number or a list of {size} numbers (one per action "
                         f"dimension), got {sigma!r}") from None  # fmt: skip
    if not np.all(np.isfinite(scales)) or np.any(scales < 0):
        raise ValueError(f"action noise sigma must be finite and >= 0, got {sigma!r}")
    return scales


def pink_noise(sigma: np.ndarray, seq_len: int, size: int, n_envs: int, seed: int | None) -> ActionNoise:
    """Pink (1/f) action noise: slow drifts with fast jitter on top, which explores a tracking task's distance and
    bearing further than white noise of the same scale. Each env draws from its own generator spawned from ``seed``:
    SB3 would otherwise deep-copy one noise per env, and the copies would repeat each other's draws."""
    from pink import PinkActionNoise  # pink-noise-rl, the learner's extra

    if seq_len < 2 or not np.any(sigma > 0):
        raise ValueError(f"pink action noise needs seq_len >= 2 and sigma > 0, got seq_len {seq_len}, sigma {sigma}")
    generators = np.random.default_rng(seed).spawn(n_envs)
    noises = [PinkActionNoise(sigma, seq_len, size, rng=generator) for generator in generators]
    if n_envs == 1:
        return noises[0]
    vectorised = VectorizedActionNoise(noises[0], n_envs)
    vectorised.noises = noises
    return vectorised


def resolve_policy_kwargs(policy_kwargs: Mapping[str, Any]) -> dict[str, Any]:
    resolved = dict(policy_kwargs)
    activation = resolved.get("activation_fn")
    if isinstance(activation, str):
        cls = getattr(torch.nn, activation, None)
        if not (isinstance(cls, type) and issubclass(cls, torch.nn.Module)):
            raise ValueError(f"activation_fn {activation!r} is not a torch.nn module class (e.g. 'GELU', 'ReLU')")
        resolved["activation_fn"] = cls
    return resolved


def default_policy(observation_space: gym.spaces.Space) -> str:
    """SB3's policy name for an observation space: dict spaces need the multi-input policy."""
    return "MultiInputPolicy" if isinstance(observation_space, gym.spaces.Dict) else "MlpPolicy"


def make_model(
    algo: str,
    env: Any,
    seed: int,
    overrides: dict[str, Any] | None = None,
    tensorboard_log: str | None = None,
) -> Any:
    """A new model of ``algo`` on ``env`` (a gymnasium env or an SB3 VecEnv) with the tuned defaults and overrides.

    ``overrides`` may also carry ``policy`` (e.g. "CnnPolicy") to replace the one chosen from the observation space.
    A per-episode ``train_freq`` on several envs is run by :func:`training_callbacks`' callback
    (learner_service/episodic.py): pass those to ``learn()``.
    """
    cls, defaults = resolve_algorithm(algo)
    n_envs = getattr(env, "num_envs", 1)
    merged = vectorised_kwargs(merge_overrides(defaults, overrides), n_envs)
    kwargs = resolve_kwargs(merged, env.action_space, n_envs, seed)
    policy = kwargs.pop("policy", default_policy(env.observation_space))
    log.info("building %s (%s) with policy %s, seed %d, settings %s", algo, cls.__name__, policy, seed, kwargs)
    return cls(policy, env, seed=seed, tensorboard_log=tensorboard_log, **kwargs)


def training_callbacks(algo: str, overrides: dict[str, Any] | None, n_envs: int) -> list[BaseCallback]:
    """The callbacks a model of ``algo`` built by :func:`make_model` on ``n_envs`` envs needs in ``learn()``."""
    _, defaults = resolve_algorithm(algo)
    return episodic_callbacks(merge_overrides(defaults, overrides), n_envs)


def load_policy(
    algo: str,
    checkpoint: str | Path | None,
    env: Any = None,
    device: str = "auto",
    gains: TrackerGains | None = None,
    task: str | None = None,
) -> Policy:
    """A deterministic policy: the scripted baseline (no checkpoint) with ``gains``, or a saved model of ``algo``.

    For ``scripted-camera`` the checkpoint is the CMVAE whose state decoders it reads (None: the shipped one).
    A saved model trained on another task than ``task`` (when given) is refused naming both.
    """
    if algo == SCRIPTED:
        return ScriptedTracker(gains or TrackerGains())
    if algo == LATENT_SCRIPTED:
        encoder = open_encoder(checkpoint or DEFAULT_CHECKPOINT)
        return LatentTracker(encoder.decode_state, encoder.n_z, gains)
    cls, _ = resolve_algorithm(algo)
    if checkpoint is None:
        raise ValueError(f"algorithm {algo!r} needs a checkpoint to load")
    path = Path(checkpoint)
    if not path.is_file() and not path.with_name(path.name + ".zip").is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist (train one with `swimm learn`)")
    saved = path if path.is_file() else path.with_name(path.name + ".zip")
    read_identity(saved)  # refuses a file that is no model
    if task is not None:
        check_task(saved, task)
    log.info("loading %s checkpoint %s", algo, path)
    return SB3Policy(cls.load(path, env=env, device=device))
