"""The tracking env in one process: World + TrackingTask (+ latent encoder), no network in between.

This is the baseline the distributed ProxyEnv is measured against and must
agree with: the same episode seeds (``episode_seed(base_seed, ep)``, ep
counting from 1), the same task arithmetic, the same time limit reported as
``truncated``. Only the transport differs, so the same seed and actions give
the same trajectory either way.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import gymnasium as gym
import numpy as np

from learner_service.learn_settings import TASK_DOLPHIN_MOTIONS
from learner_service.task import (
    LATENCY_OPTION,
    NOISE_OPTION,
    SCENE_OPTION,
    Frame,
    TaskSettings,
    TrackingTask,
    episode_seed,
)
from services.messages import DiveMode
from services.telemetry import Telemetry
from sim_service.latency import latency_option
from sim_service.noise import noise_option
from sim_service.scenery import scene_option
from sim_service.settings import WorldSettings
from sim_service.world import World

log = logging.getLogger(__name__)

IMAGE_MODES = ("cmvae", "image")


def task_world(task: TaskSettings, render: bool = False, base: WorldSettings | None = None) -> WorldSettings:
    """The world an in-process env of ``task`` runs: ``base`` (default: the plain world) with the task's dolphin
    motion, rendering when asked or when observations need it.

    A distributed sim's dolphin is its own ``--dolphin-motion``: start it with ``3d`` for the 3d task.
    """
    base = base or WorldSettings()
    dolphin = dataclasses.replace(base.dolphin, motion=TASK_DOLPHIN_MOTIONS[task.task])
    return dataclasses.replace(base, render=render or task.obs in IMAGE_MODES, dolphin=dolphin)


class TrackingEnv(gym.Env):
    """Gymnasium env of the tracking task; ``info`` carries telemetry, cause, d, theta, azimuth, psi, ep (and seed).

    The episode number is ``info["ep"]``, never ``"episode"``: SB3 reads ``info["episode"]`` as Monitor statistics.

    ``encoder`` is any object with ``encode(images uint8 (N, 64, 64, 3)) -> (mu, logvar)``; in cmvae mode without
    one, the default :class:`encoder_service.inference.LatentEncoder` checkpoint is loaded at the first reset. One
    that ``tracks`` reads each frame's prior too (``track(images, priors) -> (mu, logvar, next priors)``), as the
    distributed loop hands it: the next prior its previous frame gave, the image centre at an episode's first frame.

    ``share_renderer_with`` draws through another env's renderer (one GL context for envs stepped one after
    another, as a sim's are: see :class:`sim_service.world.World`).
    """

    metadata = {"render_modes": ["rgb_array"]}
    render_mode = "rgb_array"  # render(): the last camera frame (None before the first, or in a non-rendering world)

    def __init__(
        self,
        task_settings: TaskSettings | None = None,
        world_settings: WorldSettings | None = None,
        base_seed: int = 0,
        encoder: Any = None,
        share_renderer_with: TrackingEnv | None = None,
    ) -> None:
        self.task = TrackingTask(task_settings)
        needs_images = self.task.settings.obs in IMAGE_MODES
        world_settings = world_settings or task_world(self.task.settings)
        if needs_images and not world_settings.render:
            raise ValueError(f"observation mode {self.task.settings.obs!r} needs a rendering world (render=True)")
        self.world = World(
            world_settings, share_renderer_with=share_renderer_with.world if share_renderer_with else None
        )
        self.observation_space = self.task.observation_space
        self.action_space = self.task.action_space
        self.base_seed = base_seed
        self.episode = 0
        self._encoder = encoder
        self._last_image: np.ndarray | None = None
        self._prior: np.ndarray | None = None  # None at an episode's first frame: the engagement prior

    @property
    def encoder(self) -> Any:
        if self._encoder is None:
            from encoder_service.inference import LatentEncoder  # torch loads only when a latent is needed

            self._encoder = LatentEncoder()
        return self._encoder

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict[str, Any]]:
        """Next episode; a ``seed`` restarts the run's episode sequence at episode 1 of base seed ``seed``.

        ``options={"noise": ...}`` switches image noise as a distributed sim's reset does: true, false or a map of
        noise settings, kept for the episodes after it; ``{"latency": {...}}`` likewise sets the camera and control
        delays (sim_service.latency), and ``{"scene": {...}}`` the scenery (sim_service.scenery).
        """
        super().reset(seed=seed)
        noise = noise_option((options or {}).get(NOISE_OPTION))
        latency = latency_option((options or {}).get(LATENCY_OPTION))
        scene = scene_option((options or {}).get(SCENE_OPTION))
        if latency is not None:
            self.world.configure_latency(latency)
        if seed is not None:
            self.base_seed, self.episode = seed, 0
        self.episode += 1
        world_seed = episode_seed(self.base_seed, self.episode)
        telemetry, image = self.world.reset(world_seed, noise, scene=scene)
        self._prior = None
        obs = self.task.reset(self._frame(telemetry, image), seed=world_seed)
        info = self.task.info(telemetry, self.task.settings.task) | {"ep": self.episode, "seed": world_seed}
        log.debug(
            "episode %d (seed %d) starts at d %.2f m, theta %.1f deg",
            self.episode,
            world_seed,
            info["d"],
            info["theta"],
        )
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if self.episode == 0:
            raise RuntimeError("call reset() before step()")
        telemetry, image = self.world.step(self.task.to_sim_action(action), DiveMode.DEPTH_HOLD)
        obs, reward, terminated, info = self.task.step(action, self._frame(telemetry, image))
        info |= {"ep": self.episode}
        return obs, reward, terminated, self.task.time_up, info

    def render(self) -> np.ndarray | None:
        """The last camera frame (uint8 RGB), kept out of ``info`` so SB3 does not copy it into every step's info."""
        return self._last_image

    def _frame(self, telemetry: Telemetry, image: np.ndarray | None) -> Frame:
        self._last_image = image
        if self.task.settings.obs != "cmvae":
            return Frame(telemetry, image=image)
        if not getattr(self.encoder, "tracks", False):
            mu, logvar = self.encoder.encode(image[None])
        else:
            priors = None if self._prior is None else self._prior[None]
            mu, logvar, next_prior = self.encoder.track(image[None], priors)
            self._prior = np.asarray(next_prior[0], dtype=np.float32)
        return Frame(telemetry, image=image, mu=mu[0], logvar=logvar[0])

    def close(self) -> None:
        self.world.close()
