"""The env factory of every training job: the same task over Zenoh or in one process, as an SB3 VecEnv.

`swimm learn`, `swimm up` and `swimm bench train` call :func:`make_vec_env` with a backend name and get the
same thing either way, so the only difference between a distributed and an in-process run is the transport:

- ``"zenoh"``: a :class:`learner_service.proxy_env.ProxyVecEnv` driving ``n_envs`` envs of a running sim;
- ``"inprocess"``: a DummyVecEnv of :class:`learner_service.inprocess_env.TrackingEnv`, each with its own World,
  all drawing through the first one's renderer (one GL context, as in a sim process).

Sub-env i has base seed ``base_seed + i`` in both. Both are wrapped in one VecMonitor that records each
episode's reward, length, time and termination ``cause`` (empty for the time limit) in one CSV, which the
summary plot (:func:`learner_service.plots.plot_training`) reads. One VecMonitor for the vector rather than a
Monitor per sub-env, because the ProxyVecEnv's sub-envs are not separate gymnasium envs one could wrap.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import typing
from pathlib import Path
from typing import Any

import gymnasium as gym
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecMonitor

from encoder_service import DEFAULT_CHECKPOINT
from encoder_service.inference import open_encoder
from learner_service.learn_settings import Backend
from learner_service.task import TaskSettings

log = logging.getLogger(__name__)

BACKENDS: tuple[str, ...] = typing.get_args(Backend)
MONITOR_KEYWORDS = ("cause",)  # info keys the monitor CSV keeps per episode, beside r, l, t
IMAGE_MODES = ("cmvae", "image")


def check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")


def env_ids(n_envs: int) -> tuple[str, ...]:
    """The env ids a run of ``n_envs`` drives on its channel: "0" .. "n-1", as `swimm sim` serves them."""
    if n_envs < 1:
        raise ValueError(f"n_envs must be >= 1, got {n_envs}")
    return tuple(str(index) for index in range(n_envs))


def shared_encoder(task: TaskSettings, encoder: Any = None, checkpoint: str | Path | None = None) -> Any:
    """The one latent encoder all in-process envs share (cmvae only): ``encoder`` if given, else a checkpoint's.

    Loading it once keeps one copy of the weights (and one traced graph) however many envs run.
    """
    if task.obs != "cmvae" or encoder is not None:
        return encoder
    return open_encoder(checkpoint or DEFAULT_CHECKPOINT)


def make_env(
    backend: Backend,
    task: TaskSettings,
    proxy: Any = None,
    env_id: str = "0",
    base_seed: int = 0,
    *,
    encoder: Any = None,
    session: Any = None,
    share_renderer_with: gym.Env | None = None,
    world: Any = None,
) -> gym.Env:
    """One env (for evaluation episodes): a ProxyEnv on ``proxy.channel``/``env_id``, or a TrackingEnv (drawing
    through ``share_renderer_with``'s renderer when given, another TrackingEnv) in ``world``, a
    :class:`sim_service.settings.WorldSettings` (default: the plain world) with the task's dolphin."""
    check_backend(backend)
    if backend == "zenoh":
        from learner_service.proxy_env import ProxyEnv  # zenoh only when the backend needs it

        return ProxyEnv(task, _require_proxy(proxy), env_id, base_seed, session=session)
    from learner_service.inprocess_env import TrackingEnv, task_world  # MuJoCo: not in the torch image

    return TrackingEnv(
        task,
        task_world(task, base=world),
        base_seed=base_seed,
        encoder=shared_encoder(task, encoder),
        share_renderer_with=share_renderer_with,
    )


def make_vec_env(
    backend: Backend,
    task: TaskSettings,
    proxy: Any = None,
    n_envs: int = 1,
    base_seed: int = 0,
    *,
    monitor_path: str | Path | None = None,
    encoder: Any = None,
    session: Any = None,
    world: Any = None,
) -> VecEnv:
    """``n_envs`` envs of the task as one VecMonitor-wrapped SB3 VecEnv (see the module docstring).

    ``proxy`` (a :class:`learner_service.proxy_env.ProxySettings`) is needed for ``"zenoh"``; its ``envs`` are
    replaced by "0" .. "n_envs-1" unless it already names exactly ``n_envs`` ids. ``session`` shares an open
    Zenoh session (the caller closes it). ``encoder`` is the in-process latent encoder (default: the shipped
    CMVAE, loaded once) and ``world`` the in-process envs' world (see :func:`make_env`). ``monitor_path`` writes
    the episodes' CSV (SB3 names it ``<path>.monitor.csv``).
    """
    check_backend(backend)
    ids = env_ids(n_envs)
    if backend == "zenoh":
        from learner_service.proxy_env import ProxyVecEnv  # zenoh only when the backend needs it

        proxy = _require_proxy(proxy)
        if len(proxy.envs) != n_envs:
            proxy = dataclasses.replace(proxy, envs=ids)
        vec_env: VecEnv = ProxyVecEnv(task, proxy, base_seed, session=session)
    else:
        encoder = shared_encoder(task, encoder)
        built: list[gym.Env] = []

        def build(index: int) -> gym.Env:  # DummyVecEnv calls these in order and steps the envs one after another
            first = built[0] if built else None
            built.append(
                make_env(
                    "inprocess",
                    task,
                    base_seed=base_seed + index,
                    encoder=encoder,
                    share_renderer_with=first,
                    world=world,
                )
            )
            return built[-1]

        vec_env = DummyVecEnv([functools.partial(build, index) for index in range(n_envs)])
    log.info("%d %s env(s), obs %s, base seed %d", n_envs, backend, task.obs, base_seed)
    filename = str(monitor_path) if monitor_path is not None else None
    return VecMonitor(vec_env, filename=filename, info_keywords=MONITOR_KEYWORDS)


def _require_proxy(proxy: Any) -> Any:
    if proxy is None:
        raise ValueError("the zenoh backend needs ProxySettings (where the router is, which namespace and channel)")
    return proxy
