"""The tracking task: observations, reward and termination, computed from the sim's telemetry on the learner side.

The sim is a generic world (like dm_control's Physics); this module is its
Task. Keeping the task here means one sim serves any observation mode or
reward version, and the in-process env and the distributed proxy env share
the exact same arithmetic, so their trajectories and returns agree bit for bit.

Conventions: the policy acts in (surge, yaw) in the planar task and in (surge, heave, yaw) in the 3d task, each
in [-1, 1]; angles in the observation are radians, every angle reported in ``info`` is in degrees.
"""

from __future__ import annotations

import math
import typing
from collections import deque
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from learner_service.learn_settings import ObsMode, RewardVersion, TaskName
from services.geometry import ALPHA_DEG, BETA_DEG, MAX_D, OPT_D, quat_to_euler, relative_geometry, vertical_geometry
from services.messages import IMAGE_SHAPE, POLICY_ACTIONS
from services.telemetry import Telemetry

LATENT_SIZE = 10  # n_z of the CMVAE
LATENCY_OPTION = "latency"  # env.reset(options={"latency": {settings}}): camera and control delays from that episode
NOISE_OPTION = "noise"  # env.reset(options={"noise": True | False | {settings}}): the image noise from that episode
SCENE_OPTION = "scene"  # env.reset(options={"scene": {settings}}): the world's scenery from that episode on
STATE_SIZE = 12  # rover pos, rover roll/pitch/yaw, target pos, target roll/pitch/yaw
REWARD_K = 1.0  # the SPEC's k: curvature of both penalties

# Why an episode ends early, as reported in ``info["cause"]`` and the evaluation summary.
CAUSE_DISTANCE = "distance"
CAUSE_VISIBILITY = "visibility"
CAUSE_COLLISION = "collision"
CAUSE_SIM_LOST = "sim_lost"  # a distributed episode cut short (truncated) because its sim restarted
NO_CAUSE = ""

#: Offset mixed into the episode seed for the task's own generator, so its draws never mirror the world's.
_TASK_STREAM = 0x7A5C


def episode_seed(base_seed: int, ep: int) -> int:
    """The world seed of episode ``ep`` of a run seeded ``base_seed``: deterministic, well mixed, 32 bits.

    SeedSequence hashes (base_seed, ep) so that neighbouring runs (seeds 97, 101, ...) and neighbouring
    episodes get unrelated streams, unlike ``base_seed + ep`` which makes run 97 episode 5 equal run 101 episode 1.
    """
    if base_seed < 0 or ep < 0:
        raise ValueError(f"base_seed and ep must be non-negative, got {base_seed} and {ep}")
    return int(np.random.SeedSequence([base_seed, ep]).generate_state(1, np.uint32)[0])


@dataclass(frozen=True)
class TaskSettings:
    obs: ObsMode = "cmvae"
    reward: RewardVersion = "swimm2"
    task: TaskName = "planar"  # 3d: distance in 3d and an elevation term in the reward (docs/learner.md, "Tasks")
    n_prev_actions: int = 10  # ActPrev length
    use_latent_mean: bool = True  # False: feed z sampled from N(mu, exp(logvar)), as the reference does
    max_steps: int = 3000  # truncation (time limit)
    early_termination: bool = True  # False for evaluation episodes: they always run max_steps

    @property
    def action_names(self) -> tuple[str, ...]:
        return POLICY_ACTIONS[self.task]

    @property
    def history_size(self) -> int:
        """Values of ActPrev in an observation: the last n_prev_actions actions, flattened."""
        return self.n_prev_actions * len(self.action_names)

    def __post_init__(self) -> None:
        if self.obs not in typing.get_args(ObsMode):
            raise ValueError(f"unknown observation mode {self.obs!r}; choose {', '.join(typing.get_args(ObsMode))}")
        if self.reward not in typing.get_args(RewardVersion):
            choices = ", ".join(typing.get_args(RewardVersion))
            raise ValueError(f"unknown reward version {self.reward!r}; choose {choices}")
        if self.task not in typing.get_args(TaskName):
            raise ValueError(f"unknown task {self.task!r}; choose {', '.join(typing.get_args(TaskName))}")
        if self.n_prev_actions < 0 or self.max_steps < 1:
            raise ValueError("n_prev_actions must be >= 0 and max_steps >= 1")


@dataclass(frozen=True)
class Frame:
    """What the task sees of one step: ground truth always, plus the image or the encoder's latent by mode."""

    telemetry: Telemetry
    image: np.ndarray | None = None  # uint8 (64, 64, 3) RGB
    mu: np.ndarray | None = None  # (n_z,) latent mean
    logvar: np.ndarray | None = None  # (n_z,) latent log-variance


def swimm2_penalties(d: float, theta: float, k: float = REWARD_K) -> tuple[float, float]:
    """SWiMM 2.0's exponential distance penalty and logarithmic azimuth penalty, each capped, in [0, 1].

    ``theta`` is the unsigned azimuth error in degrees.
    """
    e_d = min(abs(d - OPT_D), MAX_D)
    pen_d = math.expm1(k * e_d) / math.expm1(k * MAX_D)
    e_theta = min(theta, ALPHA_DEG)
    pen_theta = math.log1p(k * e_theta) / math.log1p(k * ALPHA_DEG)
    return pen_d, pen_theta


def swimm2_reward(d: float, theta: float, k: float = REWARD_K) -> float:
    """SWiMM 2.0 reward in [-1, 1]: 1 less its two penalties (:func:`swimm2_penalties`)."""
    pen_d, pen_theta = swimm2_penalties(d, theta, k)
    return 1.0 - (pen_d + pen_theta)


def swimm1_reward(d: float, theta: float) -> float:
    """SWiMM 1.0 reward: quadratic distance and linear azimuth penalties, uncapped (unbounded below)."""
    return 1.0 - ((d - OPT_D) ** 2 / MAX_D**2 + abs(theta) / 180.0)


REWARDS = {"swimm2": swimm2_reward, "swimm1": swimm1_reward}


def swimm2_elevation_penalty(phi: float, k: float = REWARD_K) -> float:
    """The 3d task's elevation term for SWiMM 2.0, in [0, 1]: the azimuth penalty's form against beta."""
    return math.log1p(k * min(phi, BETA_DEG)) / math.log1p(k * BETA_DEG)


def swimm1_elevation_penalty(phi: float) -> float:
    """The 3d task's elevation term for SWiMM 1.0: linear like its azimuth term, 1 at 90 degrees."""
    return abs(phi) / 90.0


#: The 3d task's reward is the version's reward at the 3d distance, less this penalty of the elevation error.
ELEVATION_PENALTIES = {"swimm2": swimm2_elevation_penalty, "swimm1": swimm1_elevation_penalty}


def frame_reward(info: dict[str, Any], version: RewardVersion) -> float:
    """The reward of one frame from its :meth:`TrackingTask.info`: the version's, less the 3d task's elevation term."""
    reward = REWARDS[version](info["d"], info["theta"])
    if "phi" in info:
        reward -= ELEVATION_PENALTIES[version](info["phi"])
    return reward


def policy_action(command: Any, task: TaskName) -> np.ndarray:
    """The task's policy action within a sim's (sway, heave, surge, yaw) command, as recordings and taps read it."""
    _, heave, surge, yaw = command
    components = {"surge": surge, "heave": heave, "yaw": yaw}
    return np.array([components[name] for name in POLICY_ACTIONS[task]], np.float64)


def violation_cause(d: float, in_frustum: bool, collided: bool) -> str:
    """The SPEC's early-termination condition that holds, most severe first; "" when none does."""
    if collided:
        return CAUSE_COLLISION
    if not in_frustum:
        return CAUSE_VISIBILITY
    if abs(d - OPT_D) >= MAX_D:
        return CAUSE_DISTANCE
    return NO_CAUSE


def state_vector(t: Telemetry) -> np.ndarray:
    """The 12 ground-truth values of the state observation: positions in metres, Euler angles in radians.

    Angles are intrinsic z-y-x (roll, pitch, yaw) of the telemetry quaternions, as the sim defines them.

    Euler angles (roll, pitch, yaw) rather than quaternions keep the SPEC's 12 values and read directly;
    in the horizontal curriculum roll and pitch stay near 0, so their singularity at pitch +-90 deg never bites.
    """
    return np.array(
        [*t.rover_pos, *quat_to_euler(t.rover_quat), *t.target_pos, *quat_to_euler(t.target_quat)],
        dtype=np.float32,
    )


class TrackingTask:
    """Turns frames into observations, rewards and terminations; owns the action history (ActPrev)."""

    def __init__(self, settings: TaskSettings | None = None) -> None:
        self.settings = settings or TaskSettings()
        self.action_space = gym.spaces.Box(-1.0, 1.0, (len(self.settings.action_names),), dtype=np.float32)
        self.observation_space = self._observation_space()
        self.elapsed_steps = 0
        self._history: deque[np.ndarray] = deque(maxlen=self.settings.n_prev_actions)
        self._rng = np.random.default_rng([_TASK_STREAM, 0])

    # --- spaces --------------------------------------------------------------------------------
    @property
    def history_size(self) -> int:
        return self.settings.history_size

    def _observation_space(self) -> gym.Space:
        history_low = np.full(self.history_size, -1.0, np.float32)
        history_high = np.full(self.history_size, 1.0, np.float32)
        mode = self.settings.obs
        if mode == "image":
            return gym.spaces.Dict(
                {
                    "image": gym.spaces.Box(0, 255, IMAGE_SHAPE, dtype=np.uint8),
                    "actions": gym.spaces.Box(history_low, history_high, dtype=np.float32),
                }
            )
        if mode == "cmvae":
            head_low = np.full(LATENT_SIZE, -np.inf, np.float32)
            head_high = -head_low
        else:
            angles = np.full(3, np.pi, np.float32)
            position = np.full(3, np.inf, np.float32)
            head_high = np.concatenate([position, angles, position, angles])
            head_low = -head_high
        return gym.spaces.Box(
            np.concatenate([head_low, history_low]), np.concatenate([head_high, history_high]), dtype=np.float32
        )

    # --- actions -------------------------------------------------------------------------------
    def clip_action(self, action: Any) -> np.ndarray:
        """The policy's action as float32 in [-1, 1]; refuses a wrong shape or a non-finite value."""
        array = np.asarray(action, dtype=np.float32).reshape(-1)
        names = self.settings.action_names
        if array.shape != (len(names),):
            raise ValueError(f"the {self.settings.task} task's policy action must be ({', '.join(names)}), "
                             f"got shape {np.shape(action)}")  # fmt: skip
        if not np.isfinite(array).all():
            raise ValueError(f"the policy action must be finite, got {array.tolist()}")
        return array.clip(-1.0, 1.0)  # the method skips np.clip's dispatch, which outweighs clipping a few values

    def to_sim_action(self, action: Any) -> tuple[float, float, float, float]:
        """The full (sway, heave, surge, yaw) command for the sim, which runs in depth hold: sway is held at 0, and
        so is heave in the planar task; the 3d task's heave moves the depth setpoint (0 holds depth, as ALT_HOLD)."""
        command = dict(zip(self.settings.action_names, self.clip_action(action).tolist(), strict=True))
        return 0.0, command.get("heave", 0.0), command["surge"], command["yaw"]

    # --- episode -------------------------------------------------------------------------------
    def reset(self, frame: Frame, seed: int | None = None) -> np.ndarray | dict[str, np.ndarray]:
        """Clear ActPrev and the step count; ``seed`` (the episode seed) reseeds the latent-sampling generator."""
        self.elapsed_steps = 0
        self._history.clear()
        if seed is not None:
            self._rng = np.random.default_rng([_TASK_STREAM, seed])
        return self.observation(frame)

    def step(self, action: Any, frame: Frame) -> tuple[np.ndarray | dict[str, np.ndarray], float, bool, dict[str, Any]]:
        """Record ``action`` (the one that led to ``frame``), then observe, reward and judge the frame.

        ``info["cause"]`` names the violated condition even when early termination is off (evaluation needs it);
        ``terminated`` is true only when early termination is on and a condition holds.
        """
        self._history.append(self.clip_action(action))
        self.elapsed_steps += 1
        obs = self.observation(frame)
        info = self.info(frame.telemetry, self.settings.task)
        reward = frame_reward(info, self.settings.reward)
        terminated = self.settings.early_termination and info["cause"] != NO_CAUSE
        return obs, reward, terminated, info

    @property
    def time_up(self) -> bool:
        """True once the episode has run ``max_steps`` steps: the envs report it as ``truncated``."""
        return self.elapsed_steps >= self.settings.max_steps

    @staticmethod
    def info(telemetry: Telemetry, task: TaskName = "planar") -> dict[str, Any]:
        """Geometry (degrees) and the violated condition of one frame, with the telemetry itself for baselines.

        The 3d task's ``d`` is the 3d distance (so the distance penalty, metric and limit hold in 3d), and it adds
        ``elevation`` (signed) and ``phi`` (unsigned). Leaving view vertically needs no term of its own: the sim's
        frustum test (``target_in_frustum``) is the camera's whole pyramid, top and bottom included.
        """
        geometry = relative_geometry(telemetry)
        info = {
            "telemetry": telemetry,
            "d": geometry.d,
            "theta": geometry.theta,
            "azimuth": geometry.azimuth,
            "psi": geometry.psi,
        }
        if task == "3d":
            vertical = vertical_geometry(telemetry)
            info |= {"d": vertical.distance, "elevation": vertical.elevation, "phi": vertical.phi}
        return info | {"cause": violation_cause(info["d"], telemetry.target_in_frustum, telemetry.collided)}

    # --- observations --------------------------------------------------------------------------
    def action_history(self) -> np.ndarray:
        """ActPrev flattened oldest to newest, zeros in front until n_prev_actions actions have been taken."""
        flat = np.zeros(self.history_size, np.float32)
        if self._history:
            taken = np.concatenate(list(self._history))
            flat[self.history_size - taken.size :] = taken
        return flat

    def observation(self, frame: Frame) -> np.ndarray | dict[str, np.ndarray]:
        mode = self.settings.obs
        if mode == "image":
            return {"image": self._image(frame), "actions": self.action_history()}
        head = self._latent(frame) if mode == "cmvae" else state_vector(frame.telemetry)
        return np.concatenate([head, self.action_history()])

    @staticmethod
    def _image(frame: Frame) -> np.ndarray:
        image = frame.image
        if image is None:
            raise ValueError("observation mode 'image' needs frames with an image; is the sim rendering?")
        if image.shape != IMAGE_SHAPE or image.dtype != np.uint8:
            raise ValueError(f"images must be uint8 {IMAGE_SHAPE}, got {image.dtype} {image.shape}")
        return image

    def _latent(self, frame: Frame) -> np.ndarray:
        if frame.mu is None:
            raise ValueError("observation mode 'cmvae' needs frames with the encoder's mu; is an encoder running?")
        mu = np.asarray(frame.mu, np.float32).reshape(-1)
        if mu.shape != (LATENT_SIZE,):
            raise ValueError(f"the latent mean must have {LATENT_SIZE} values, got shape {np.shape(frame.mu)}")
        if self.settings.use_latent_mean:
            return mu
        if frame.logvar is None:
            raise ValueError("sampled latents (use_latent_mean=False) need frames with the encoder's logvar")
        std = np.exp(0.5 * np.asarray(frame.logvar, np.float32).reshape(mu.shape))
        return (mu + std * self._rng.standard_normal(LATENT_SIZE)).astype(np.float32)
