"""The World: one BlueROV2 and one dolphin (or a pod, sim_service/pod.py) in MuJoCo, stepped one action at a time.

This is the generic physics half of the dm_control split: it knows bodies,
thrusters, the camera and the dolphin's swim, and reports ground truth as
:class:`~services.telemetry.Telemetry`; the tracking task (reward,
termination, observations) lives with the learner. The same class serves
`swimm sim`, `swimm dataset`, tests and the in-process baseline, so the
distributed and in-process runs are the same code and agree bit for bit.

Every random draw comes from the episode seed: ``reset(seed)`` seeds one
generator for the pose draws and the dolphin's waypoints, so a seed and an
action sequence fix the whole episode, images included. Image noise draws
from a child of that generator's seed, so switching noise on or off never
changes the trajectory: clean and noisy runs of one seed see the same poses.
The scenery (sim_service/scenery.py: seabed, light, particles, fish, the
dolphin's look) draws from another child, so it never changes them either.

A pod's companions draw from a child of their own, spawned only when there are any, so a pod of one is the
single-dolphin world bit for bit and a bigger pod never changes the target's swim or the rover's draws. Every
step's telemetry says which dolphin is nearest the image centre and whether a companion hides the target
(services/identity.py).

The dolphin's next move does not depend on the rover's action, so a server can
work it out while it waits for that action (:meth:`World.prepare_step`) and
answer the action sooner; a step that finds nothing prepared does it itself,
with the same draws in the same order, so prepared and unprepared runs agree
bit for bit.

Not thread-safe: MuJoCo's GL context belongs to the thread that built it. Worlds stepped on one thread (a sim's
group of envs) can share one renderer, and so one GL context (``World(settings, share_renderer_with=other)``):
each renders its own model and data into it, so its frames are the same as with a renderer of its own.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import mujoco
import numpy as np

from services.geometry import ALPHA_DEG
from services.identity import NONE, TARGET, followed_dolphin, in_view, target_occluded
from services.messages import DiveMode
from services.telemetry import Telemetry
from sim_service.camera import CameraFrustum
from sim_service.dolphin import DolphinBehaviour
from sim_service.latency import LatencyLine, LatencySettings
from sim_service.noise import NOISY_PRESET, ImageNoise, NoiseSettings, draw_episode_noise
from sim_service.pod import Pod
from sim_service.rover import RoverDynamics
from sim_service.scenery import SceneSettings, draw_episode_scene
from sim_service.scenery_model import DOLPHIN_PARTS, PodLooks, Scenery, build_model, part_names
from sim_service.settings import WorldSettings

MODEL_PATH = Path(__file__).parent / "assets" / "world.xml"
CAMERA = "nose"
#: The dolphin's bounding volume (the reference collider capsule's box): length, width, height in metres.
TARGET_BOX = (2.57, 0.88, 0.88)

# Reset distributions of the SPEC (training episodes).
RESET_XY_RANGE = 30.0
RESET_DEPTH = 4.0
RESET_DISTANCE = (4.0, 8.0)  # opt_d +- max_d / 2
RESET_TURN_WEIGHT = 1.3  # deg per step


def load_triton_before_rendering() -> None:
    """Import triton, when installed, before MuJoCo's first render in this process.

    Mesa's software EGL (llvmpipe) and triton (which pip installs beside torch) each load their own LLVM.
    Torch imports triton lazily, and doing so after a frame was rendered segfaults the process; importing
    it first does not. Any process that renders and later trains or encodes (in-process envs, benchmarks,
    tests) is covered by doing it here, once, where rendering starts.
    """
    if importlib.util.find_spec("triton") is not None:
        importlib.import_module("triton")


@dataclass(frozen=True)
class DolphinPose:
    """The dolphin at one step, in the forms a step needs: mocap poses, its rotation, its telemetry fields."""

    mocap: tuple[tuple[np.ndarray, np.ndarray], ...]  # (position, quaternion) of each mocap body
    rotation: np.ndarray  # body-to-world, for the frustum test
    telemetry: dict[str, Any]  # the target_* fields of Telemetry
    companions: tuple[tuple[tuple[np.ndarray, np.ndarray], ...], ...] = ()  # each companion's mocap poses


@dataclass(frozen=True)
class PreparedStep:
    """The next step's action-independent half, and the generator state to restore if it is thrown away."""

    dolphin: DolphinPose
    rng_state: dict[str, Any]


class World:
    def __init__(self, settings: WorldSettings | None = None, share_renderer_with: World | None = None) -> None:
        self.settings = settings or WorldSettings()
        self.settings.dolphin.check()
        companions = self.settings.dolphin.pod_size - 1
        self.model = build_model(MODEL_PATH, companions)
        self.model.opt.timestep = self.settings.physics_dt
        self.data = mujoco.MjData(self.model)
        self.rover = RoverDynamics()
        self.dolphin = DolphinBehaviour(motion=self.settings.dolphin.motion)
        self.pod = Pod(self.settings.dolphin.pod_size, crossing=self.settings.dolphin.pod_crossing)
        self._pod_looks = PodLooks(self.model, companions)
        self.rng = np.random.default_rng(0)
        self._rover_body = self.model.body("rover").id
        rover_geom = self.model.geom("rover_hull").id
        target_geom = self.model.geom("dolphin_collider").id
        self._pair = (min(rover_geom, target_geom), max(rover_geom, target_geom))
        dolphin_bodies = [self.model.body(name).id for name in DOLPHIN_PARTS]
        self._mocap = [self.model.body_mocapid[body] for body in dolphin_bodies]
        self._companion_mocap = [
            [self.model.body_mocapid[self.model.body(name).id] for name in part_names(i)]
            for i in range(1, companions + 1)
        ]
        self._target_geoms = np.flatnonzero(np.isin(self.model.geom_bodyid, dolphin_bodies))
        companion_parts = [self.model.body(name).id for i in range(1, companions + 1) for name in part_names(i)]
        self._companion_geoms = np.flatnonzero(np.isin(self.model.geom_bodyid, companion_parts))
        self._companion_bodies = [self.model.body(part_names(i)[0]).id for i in range(1, companions + 1)]
        self._camera = self.model.camera(CAMERA).id
        self._view = mujoco.MjvCamera()  # the nose camera, as the renderer's scene is made from it
        self._view.type, self._view.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, self._camera
        self.frustum = CameraFrustum.from_model(self.model, self._camera)
        self._prepared: PreparedStep | None = None
        self.scenery = Scenery(self.model)
        self.configure_scene(self.settings.scene)
        self._renderer: mujoco.Renderer | None = None
        if self.settings.render and share_renderer_with is not None:
            self._renderer = self._shared_renderer(share_renderer_with)
        elif self.settings.render:
            self._renderer = self._make_renderer()
        self._noise: ImageNoise | None = None
        self._noise_rng = np.random.default_rng(0)
        self.configure_noise(self.settings.noise)
        self.configure_latency(self.settings.latency)
        self.latency = LatencyLine(LatencySettings(), None)  # the current episode's delays (none before the first)
        #: The last frame before image noise (the same array as the frame when noise is off): paired datasets
        #: keep it beside the noisy frame as the denoising target.
        self.clean_frame: np.ndarray | None = None
        # Apparent image motion per radian of yaw: the frame's width spans the horizontal field of view.
        self._px_per_rad = self.settings.image_size / math.radians(2 * ALPHA_DEG)

    def _make_renderer(self) -> mujoco.Renderer:
        load_triton_before_rendering()
        # settings.render_threads reaches Mesa as LP_NUM_THREADS, read at the process's first GL context: the
        # entry point sets it from the process's settings (services/process.py, configure_process), not the World.
        pixels = self.settings.image_size * self.settings.render_scale
        self.model.vis.global_.offwidth = max(pixels, 1)
        self.model.vis.global_.offheight = max(pixels, 1)
        renderer = mujoco.Renderer(self.model, height=pixels, width=pixels)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_FOG] = True
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = True
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        return renderer

    def _shared_renderer(self, other: World) -> mujoco.Renderer:
        """``other``'s renderer, if it draws frames this world's would: the same size and the same model (one GL
        context holds one model's meshes and textures; a pod's companions add bodies)."""
        mine, theirs = (_drawn_alike(world.settings) for world in (self, other))
        if other._renderer is None:
            raise ValueError("a World can share the renderer of a rendering World only: the other renders nothing")
        if mine != theirs:
            raise ValueError(f"Worlds share a renderer only with one (image_size, render_scale, dolphin pod_size): "
                             f"{mine} against {theirs}")  # fmt: skip
        return other._renderer

    def configure_noise(self, noise: NoiseSettings) -> None:
        """Make ``noise`` the world's image noise from the next episode on (`reset` and `place` draw it).

        It is on when it changes images; switched on later (``reset(noise=True)``) with every effect at 0, it means
        :data:`~sim_service.noise.NOISY_PRESET`. Settings are checked here, so a bad one fails before any episode.
        """
        noise = noise.resolved()
        preset = dataclasses.replace(NOISY_PRESET, randomise=noise.randomise)
        self._configured_noise = noise if noise.enabled else preset
        ImageNoise(self._configured_noise)  # validates
        self._noise_on = noise.enabled

    def configure_scene(self, scene: SceneSettings) -> None:
        """Make ``scene`` the world's scenery from the next episode on (checked here); plain draws nothing."""
        scene.resolved()
        self._configured_scene = scene

    def configure_latency(self, latency: LatencySettings) -> None:
        """Make ``latency`` the world's camera and control delays from the next episode on (checked here)."""
        latency.check()
        self._configured_latency = latency

    @property
    def noise_settings(self) -> NoiseSettings | None:
        """The image noise of the current episode (randomised ones drawn), or None when frames are clean."""
        return self._noise.settings if self._noise is not None else None

    # --- episodes --------------------------------------------------------------------------
    def reset(
        self, seed: int, noise: bool | NoiseSettings | None = None, scene: SceneSettings | None = None
    ) -> tuple[Telemetry, np.ndarray | None]:
        """Start an episode from the SPEC's reset distributions, every draw from ``seed``.

        ``noise`` switches image noise for this episode and the ones after it: True applies the world's
        noise settings (or :data:`~sim_service.noise.NOISY_PRESET` when they are all off), False renders
        clean frames, None keeps the current choice, and settings replace the world's noise (on when they
        change images). Alternating clean and noisy episodes is how the paper trains for robustness.
        ``scene`` replaces the world's scenery settings for this episode and the ones after it (None keeps them).
        """
        if scene is not None:
            self.configure_scene(scene)
        if isinstance(noise, NoiseSettings):
            self.configure_noise(noise)
        elif noise is not None:
            self._noise_on = noise
        self._discard_prepared()
        self.rng = np.random.default_rng(seed)
        rng = self.rng
        rover_pos = np.array([*rng.uniform(-RESET_XY_RANGE, RESET_XY_RANGE, size=2), -RESET_DEPTH])
        rover_yaw = rng.uniform(-math.pi, math.pi)
        distance = rng.uniform(*RESET_DISTANCE)
        azimuth = math.radians(rng.uniform(-ALPHA_DEG, ALPHA_DEG))
        relative_yaw = rng.uniform(-math.pi, math.pi)
        turn_weight = rng.uniform(-RESET_TURN_WEIGHT, RESET_TURN_WEIGHT)
        phase = rng.uniform(0.0, 1.0)
        bearing = rover_yaw + azimuth
        target_pos = rover_pos + distance * np.array([math.cos(bearing), math.sin(bearing), 0.0])
        return self.place(rover_pos, rover_yaw, target_pos, rover_yaw + relative_yaw, turn_weight, phase)

    def place(
        self,
        rover_pos: np.ndarray,
        rover_yaw: float,
        target_pos: np.ndarray,
        target_yaw: float,
        turn_weight: float = 0.0,
        phase: float = 0.0,
        noise_rng: np.random.Generator | None = None,
        sight_share: float | None = None,
    ) -> tuple[Telemetry, np.ndarray | None]:
        """Put rover (at rest, level) and dolphin at given poses: the reset primitive, and datasets' sampler.

        Angles in radians; ``turn_weight`` is the dolphin's turn rate in deg/step (it sets its bank).
        ``noise_rng`` feeds the image noise (a randomised noise setting's draw first); by default a child of the
        world's generator, drawn without advancing it. The scenery draws from a child of ``noise_rng`` when it is
        given (so each dataset sample has its own), else from the next child of the world's generator.

        A pod is drawn as at engagement (the target the dolphin the camera is centred on) from the next child of the
        world's generator. With ``sight_share`` (a dataset's sample) it is drawn as at any moment of an episode
        instead, from the next child of ``noise_rng``: companions where their offsets put them, near the camera's
        axis or not, and with that probability the first one halfway along the line of sight, hiding the target.
        """
        self._discard_prepared()
        self._noise_rng = noise_rng or self._spawn_rng()
        self._noise = self._episode_noise() if self._noise_on else None
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = [rover_pos[0], rover_pos[1], rover_pos[2], rover_yaw, 0.0, 0.0]
        self.rover.reset(depth=float(rover_pos[2]))
        self.dolphin.reset(self.rng, np.asarray(target_pos, float), target_yaw, turn_weight, phase, rover_pos[:2])
        latency_rng = self._spawn_rng()
        scene_rng = self._sample_child(noise_rng)
        self.scenery.apply(draw_episode_scene(self._configured_scene, scene_rng), self.data.qpos[:3], rover_yaw)
        if self.pod.size > 1 and sight_share is not None:
            self._draw_pod_mid_swim(self._sample_child(noise_rng), np.asarray(rover_pos, float), sight_share)
        elif self.pod.size > 1:  # one dolphin spawns nothing, so its episodes stay as they were
            self._reset_pod(np.asarray(rover_pos, float))
        dolphin = self._dolphin_pose()
        self._pose_dolphin(dolphin)
        mujoco.mj_forward(self.model, self.data)
        frame = self._render()
        self.latency = LatencyLine(self._configured_latency.draw(latency_rng), frame)
        return self._telemetry(dolphin), frame

    def prepare_step(self) -> None:
        """Work out the next step's action-independent half now: the dolphin's swim and its poses.

        A lock-step server calls this while it waits for the next action, so that the step after the action
        arrives is shorter (docs/benchmarks.md). Calling it again before that step does nothing, and before
        the first episode it does nothing; ``reset`` and ``place`` throw a prepared step away and give its
        random draws back, so whether and when it was called never changes an episode.
        """
        if self._prepared is not None or self.dolphin.state is None:
            return
        rng_state = self.rng.bit_generator.state
        self._prepared = PreparedStep(self._swim(), rng_state)

    def step(
        self, action: tuple[float, float, float, float], dive_mode: DiveMode = DiveMode.DEPTH_HOLD
    ) -> tuple[Telemetry, np.ndarray | None]:
        """Advance one physics step with (sway, heave, surge, yaw) commands in [-1, 1].

        The data's position- and velocity-dependent fields always describe the current state, as dm_control
        keeps them: the thrusters' wrench is worked out from them, ``mj_step2`` integrates, and ``mj_step1``
        brings them up to the new state. A plain ``mj_step`` would leave them one step behind its ``qpos``,
        so the frame, the pose and the contacts an action is answered with would not yet show that action.
        """
        d = self.data
        rotation = d.xmat[self._rover_body].reshape(3, 3)
        applied = self.latency.action(action)  # what reaches the thrusters now (latency.py)
        force, torque = self.rover.wrench(
            applied, DiveMode(dive_mode), rotation, d.xpos[self._rover_body], d.qvel[:3], self._rover_ang_vel(), self.dt
        )
        d.xfrc_applied[self._rover_body, :3] = force
        d.xfrc_applied[self._rover_body, 3:] = torque
        dolphin = self._prepared.dolphin if self._prepared is not None else self._swim()
        self._prepared = None
        mujoco.mj_step2(self.model, d)
        self._pose_dolphin(dolphin)
        self.scenery.follow(d.qpos[:3], d.qpos[3], d.time)  # rover_x, _y, _z, _yaw joints
        mujoco.mj_step1(self.model, d)
        return self._telemetry(dolphin), self.latency.frame(self._render())

    def target_mask(self) -> np.ndarray:
        """Which pixels of the current frame show the dolphin: bool (size, size), from MuJoCo's segmentation render.

        The ground truth of where the target is in the image, e.g. to check labels against what the camera sees.
        A companion in front of the target takes its pixels: the mask is what the camera sees of the target.
        """
        return self.dolphin_masks()[0]

    def dolphin_masks(self) -> tuple[np.ndarray, np.ndarray]:
        """The pixels of the current frame that show the target, and those that show any companion, from one
        segmentation render: bool (size, size) each (the companions' all False for a lone dolphin)."""
        if self._renderer is None:
            raise RuntimeError("dolphin masks need a rendering world (WorldSettings(render=True))")
        self._update_scene()
        self._renderer.enable_segmentation_rendering()
        try:
            segmentation = self._renderer.render()
        finally:
            self._renderer.disable_segmentation_rendering()
        geoms = np.where(segmentation[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, segmentation[..., 0], -1)
        return self._pooled(np.isin(geoms, self._target_geoms)), self._pooled(np.isin(geoms, self._companion_geoms))

    def companion_bodies(self) -> tuple[np.ndarray, np.ndarray]:
        """Each companion's body position (companions, 3) and (w, x, y, z) quaternion (companions, 4), now."""
        return self.data.xpos[self._companion_bodies].copy(), self.data.xquat[self._companion_bodies].copy()

    def _pooled(self, mask: np.ndarray) -> np.ndarray:
        """``mask`` at the image's size: rendered at a multiple, a pixel shows a dolphin if any of its samples does."""
        size = self.settings.image_size
        if mask.shape[0] == size:
            return mask
        scale = mask.shape[0] // size
        return mask.reshape(size, scale, size, scale).any(axis=(1, 3))

    @property
    def dt(self) -> float:
        return self.model.opt.timestep

    def close(self) -> None:
        """Free the renderer; Worlds sharing one are closed together (a second close does nothing)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # --- internals ---------------------------------------------------------------------------
    def _episode_noise(self) -> ImageNoise:
        configured = self._configured_noise
        if configured.randomise:
            return ImageNoise(draw_episode_noise(configured, self._noise_rng))
        if self._noise is None or self._noise.settings != configured:
            return ImageNoise(configured)
        return self._noise  # the same fixed noise as the last episode: keep its caches

    def _spawn_rng(self) -> np.random.Generator:
        """A generator of the episode's own, from the world's seed without advancing the world's draws."""
        return _child(self.rng)

    def _sample_child(self, noise_rng: np.random.Generator | None) -> np.random.Generator:
        """The next child of a dataset sample's generator when ``place`` is given one, else of the world's."""
        return _child(noise_rng) if noise_rng is not None else self._spawn_rng()

    def _discard_prepared(self) -> None:
        if self._prepared is not None:
            self.rng.bit_generator.state = self._prepared.rng_state
            self._prepared = None

    def _swim(self) -> DolphinPose:
        """The dolphin's move for the next step: the half of a step that does not depend on the action."""
        self.dolphin.step(self.dt, self.rng, self.data.xpos[self._rover_body])
        self.pod.step(self.dt, self.dolphin, self.data.xpos[self._rover_body])
        return self._dolphin_pose()

    def _reset_pod(self, rover_position: np.ndarray) -> None:
        """Draw the companions from a generator of their own, none nearer the camera's axis than the target (the
        first frame names the target), and dress each in its size and shade."""
        mujoco.mj_kinematics(self.model, self.data)  # the camera's pose at the rover's new place
        mujoco.mj_camlight(self.model, self.data)
        target_left = self._in_camera(self.dolphin.state.position[None])[0, 1] >= 0
        self.pod.reset(self._spawn_rng(), self.dolphin, rover_position, crossing_side=1.0 if target_left else -1.0)
        self.pod.centre_target(self.dolphin, self._in_camera)
        self._dress_pod()

    def _draw_pod_mid_swim(self, rng: np.random.Generator, rover_position: np.ndarray, sight_share: float) -> None:
        """Draw the companions from ``rng`` as at any moment of an episode; the first on the line of sight with
        probability ``sight_share`` (drawn after the pod, so the share never changes the companions' draws)."""
        self.pod.reset(rng, self.dolphin, rover_position)
        if rng.uniform() < sight_share:
            self.pod.put_on_sight(rng, self.dolphin, rover_position)
        self._dress_pod()

    def _dress_pod(self) -> None:
        for index, companion in enumerate(self.pod.companions, start=1):
            self._pod_looks.dress(index, companion.scale, companion.shade)

    def _dolphin_pose(self) -> DolphinPose:
        parts = self.dolphin.part_poses()
        mocap = tuple((part.position, part.quat) for part in parts)
        body_position, body_quat = mocap[0]
        companions = tuple(
            tuple((part.position, part.quat) for part in parts) for parts in self.pod.part_poses(self.dolphin)
        )
        return DolphinPose(
            mocap=mocap,
            companions=companions,
            rotation=parts[0].rotation,
            telemetry={
                "target_pos": _vec(body_position),
                "target_quat": _vec(body_quat),
                "target_forward": _vec(self.dolphin.forward),
                "target_lin_vel": _vec(self.dolphin.velocity),
            },
        )

    def _pose_dolphin(self, dolphin: DolphinPose) -> None:
        """Pose the mocap bodies of the target and its companions."""
        self._pose_parts(self._mocap, dolphin.mocap, self.scenery.dolphin_scale)
        for mocap, parts, companion in zip(self._companion_mocap, dolphin.companions, self.pod.companions, strict=True):
            self._pose_parts(mocap, parts, companion.scale)

    def _pose_parts(self, mocap_ids: list[int], parts, scale: float) -> None:
        """Pose one dolphin; a scaled dolphin's tail pivots sit as much farther from its body (drawn only)."""
        body = parts[0][0]
        for mocap, (position, quat) in zip(mocap_ids, parts, strict=True):
            self.data.mocap_pos[mocap] = position if scale == 1.0 else body + scale * (position - body)
            self.data.mocap_quat[mocap] = quat

    def _in_camera(self, positions: np.ndarray) -> np.ndarray:
        """World positions (N, 3) in the camera's (forward, left, up) frame; MuJoCo's camera looks along its -z."""
        local = (positions - self.data.cam_xpos[self._camera]) @ self.data.cam_xmat[self._camera].reshape(3, 3)
        return np.stack([-local[:, 2], -local[:, 0], local[:, 1]], axis=1)

    def _identity(self, dolphin: DolphinPose) -> dict[str, Any]:
        """The telemetry's pod fields: who the camera is centred on, and whether a companion hides the target."""
        bodies = np.array([dolphin.mocap[0][0], *(parts[0][0] for parts in dolphin.companions)])
        points = self._in_camera(bodies)
        if self.pod.size == 1:  # the cheap answer a lone dolphin allows
            followed = TARGET if in_view(points)[0] else NONE
            return {"pod_size": 1, "followed": followed, "target_occluded": False}
        return {
            "pod_size": self.pod.size,
            "followed": followed_dolphin(points),
            "target_occluded": target_occluded(points),
        }

    def _rover_ang_vel(self) -> np.ndarray:
        velocity = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_BODY, self._rover_body, velocity, 0)
        return velocity[:3]

    def _collided(self) -> bool:
        if self.data.ncon == 0:  # the usual case: skip the array work
            return False
        geoms = self.data.contact.geom[: self.data.ncon]
        return bool(np.any((geoms.min(axis=1) == self._pair[0]) & (geoms.max(axis=1) == self._pair[1])))

    def _telemetry(self, dolphin: DolphinPose) -> Telemetry:
        d = self.data
        rover_rot = d.xmat[self._rover_body].reshape(3, 3)
        in_view = self.frustum.sees_box(
            d.cam_xpos[self._camera],
            d.cam_xmat[self._camera].reshape(3, 3),
            dolphin.mocap[0][0],
            dolphin.rotation,
            TARGET_BOX,
        )
        return Telemetry(
            rover_pos=_vec(d.xpos[self._rover_body]),
            rover_quat=_vec(d.xquat[self._rover_body]),
            rover_forward=_vec(rover_rot[:, 0]),
            rover_lin_vel=_vec(d.qvel[:3]),
            rover_ang_vel=_vec(self._rover_ang_vel()),
            **dolphin.telemetry,
            target_in_frustum=bool(in_view),
            collided=self._collided(),
            sim_time=float(d.time),
            **self._identity(dolphin),
        )

    def _render(self) -> np.ndarray | None:
        if self._renderer is None:
            return None
        self._update_scene()
        image = self._downscale(self._renderer.render())
        self.clean_frame = image
        if self._noise is None:
            return image
        depth = self._render_depth() if self._noise.settings.needs_depth else None
        yaw_rate = float(self._rover_ang_vel()[2])  # + turns the nose left, so the scene slides right
        return self._noise.apply(image, depth, self._noise_rng, (yaw_rate * self.dt * self._px_per_rad, 0.0))

    def _update_scene(self) -> None:
        """The renderer's scene made from this world's own model and data (``Renderer.update_scene`` would read the
        model the renderer was built with, which a shared renderer's is not)."""
        mujoco.mjv_updateScene(self.model, self.data, self.scenery.option, None, self._view,
                               mujoco.mjtCatBit.mjCAT_ALL, self._renderer.scene)  # fmt: skip

    def _render_depth(self) -> np.ndarray:
        """Distance along the view axis in metres, per pixel of the output image."""
        self._renderer.enable_depth_rendering()
        try:
            return self._downscale(self._renderer.render())
        finally:
            self._renderer.disable_depth_rendering()

    def _downscale(self, pixels: np.ndarray) -> np.ndarray:
        size = self.settings.image_size
        if pixels.shape[0] == size:
            return pixels
        return cv2.resize(pixels, (size, size), interpolation=cv2.INTER_AREA)


def _drawn_alike(settings: WorldSettings) -> tuple[int, int, int]:
    """What two Worlds must agree on to share a renderer: the frame's size and the model's bodies."""
    return settings.image_size, settings.render_scale, settings.dolphin.pod_size


def _child(rng: np.random.Generator) -> np.random.Generator:
    """The next child generator of ``rng``'s seed; ``rng``'s own draws are left as they are."""
    return np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])


def _vec(values) -> tuple[float, ...]:
    return tuple(np.asarray(values, dtype=float).tolist())
