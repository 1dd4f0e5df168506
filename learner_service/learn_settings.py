"""Settings of `swimm learn` (and of the learner `swimm up` starts): plain dataclasses, nothing heavy imported.

They live apart from :mod:`learner_service.command` so that `swimm up` (in services/, which must not import
torch) can take every learner flag and hand them on, without loading stable-baselines3 itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from services.settings import (
    FilePath,
    NonNegFloat,
    NonNegInt,
    PosFloat,
    PosInt,
    SettingsError,
    ZenohSettings,
    check_ranges,
)
from sim_service.settings import world_of_file

#: The choices of the learner's settings, typed so that the settings loader checks them wherever they come from.
ObsMode = Literal["cmvae", "image", "state"]
RewardVersion = Literal["swimm2", "swimm1"]
#: planar: the paper's task at one depth; 3d: the dolphin climbs and dives, and elevation counts too.
TaskName = Literal["planar", "3d"]
#: The dolphin motion (sim_service.settings.Motion) each task tracks: the 3d task follows its climbs and dives.
TASK_DOLPHIN_MOTIONS = {"planar": "planar", "3d": "3d"}
Backend = Literal["zenoh", "inprocess"]

EVAL_UNITS = ("episodes", "steps")


@dataclass
class EvalSettings:
    """When and how the evaluation callback runs (flags ``--eval-*`` of `swimm learn`)."""

    enabled: bool = True
    episodes: PosInt = 5  # deterministic episodes per evaluation
    min_steps: NonNegInt = 500_000  # no evaluation before this many training steps (the reference: 5e5)
    every: PosInt = 10  # evaluate every this many training episodes (or steps, see unit) once min_steps have run
    unit: Literal["episodes", "steps"] = "episodes"
    seed: int = 113  # base seed of the evaluation episodes: every evaluation plays the same episodes
    max_steps: PosInt = 3000  # length of an evaluation episode (no early termination: the SPEC's evaluation)
    env: str = "0"  # distributed: the id of the eval-channel env the learner claims for its evaluations

    def check(self) -> None:
        if self.unit not in EVAL_UNITS:
            raise ValueError(f"eval unit must be one of {EVAL_UNITS}, got {self.unit!r}")
        check_ranges(self, "eval_")


@dataclass
class DemoSettings:
    """Flags ``--demo-*`` of `swimm learn`."""

    steps: NonNegInt = 0  # env steps the scripted tracker plays before training (0: no demonstrations)
    teacher: str = "scripted"  # scripted (ground truth) | scripted-camera (the CMVAE's decoded d, theta; cmvae obs)
    noise: NonNegFloat = 0.3  # std of the Gaussian noise on the tracker's actions as it plays (demonstrations.py)
    bc_epochs: NonNegInt = 20  # epochs fitting the policy to the tracker's actions (0: fill the replay buffer only)
    bc_batch_size: PosInt = 256
    bc_learning_rate: PosFloat = 1e-3
    critic_steps: NonNegInt = 5000  # off-policy: gradient steps on the critic alone after cloning, the actor held
    bc_weight: NonNegFloat = 0.0  # off-policy: weight of a cloning loss added to each actor update in training (0: off)

    def check(self) -> None:
        check_ranges(self, "demo_")


@dataclass
class TrackerGains:
    """The scripted tracker's control law (flags ``--scripted-*``): proportional gains, and damping for a late loop.

    ``yaw_damping`` subtracts that many times the mean yaw command of ActPrev, the last actions the observation
    carries: the turn already commanded and still to come, which a loop that is late (docs/eval_report.md, "slow
    loop") would otherwise overshoot. It reads only what a policy sees, so a policy can clone it.
    """

    # Defaults from a sweep on the in-process env (3 evaluation episodes, seed 113): yaw gains above ~1/45 per
    # degree make the heading oscillate (A and S_A grow), lower ones lag the dolphin; surge gain matters less.
    yaw_gain: NonNegFloat = 1.0 / 60.0  # command per degree of azimuth: full turn at 60 degrees
    surge_gain: NonNegFloat = 1.0  # command per metre of distance error: full surge 1 m off opt_d
    yaw_damping: NonNegFloat = 0.0  # command per unit of ActPrev's mean yaw command (0: none, the undelayed optimum)
    heave_gain: NonNegFloat = 0.1  # 3d task: command per degree of elevation: full climb or dive at 10 degrees
    heave_dead_band: NonNegFloat = 1.0  # 3d task: degrees of elevation within which heave stays 0 (depth held)

    def check(self) -> None:
        check_ranges(self, "scripted_")


@dataclass
class SmoothSettings:
    """Flags ``--smooth-*`` of `swimm learn`: CAPS action smoothness of the actor (see smoothness.py)."""

    temporal: NonNegFloat = 0.0  # weight of the squared action change between consecutive observations (0: off)
    spatial: NonNegFloat = 0.0  # weight of the squared action change under observation noise of std sigma (0: off)
    sigma: PosFloat = 0.05  # std of the spatial term's observation noise
    bound: NonNegFloat = 0.0  # weight of the squared excess past the action space (PPO) or tanh's saturation (SAC, TD3)
    batch_size: PosInt = 256  # minibatch of each term (replay buffer or rollout), per actor update

    @property
    def enabled(self) -> bool:
        return self.temporal > 0 or self.spatial > 0 or self.bound > 0

    def check(self) -> None:
        check_ranges(self, "smooth_")


@dataclass
class LearnCommandSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    algo: str = "sac"  # sac | ppo | td3 | package.module:Class
    obs: ObsMode = "cmvae"
    reward: RewardVersion = "swimm2"
    task: TaskName = "planar"  # planar | 3d: in-process, the 3d dolphin too; a sim must run --dolphin-motion 3d
    max_steps: PosInt = 3000  # time limit of a training episode (truncation)
    steps: NonNegInt = 0  # training env steps (more when resuming); 0 = the algorithm's n_timesteps (1e6)
    budget_min: NonNegFloat = 0.0  # wall-time budget in minutes (model building and demonstrations count); 0 = none
    envs: PosInt = 1  # parallel envs (train channel ids 0..envs-1 when distributed)
    group_size: NonNegInt = 0  # distributed: envs stepped as one message each way (e.g. envs/2: two groups); 0 = none
    seed: int = 97  # model seed and base seed of env 0 (env i: seed + i)
    backend: Backend = "zenoh"  # zenoh (a running sim/encoder) | inprocess (World in this process)
    run_dir: str = ""  # default runs/<algo>-<obs>-<UTC time>
    resume: FilePath = ""  # a saved model (.zip) to go on training; its replay buffer is loaded if beside it
    hyperparams: str = ""  # YAML mapping or file over the algorithm's defaults, e.g. "{gradient_steps: 32}"
    checkpoint_every: NonNegInt = 50_000  # env steps between checkpoints; 0 = none
    save_replay_buffer: bool = True  # with checkpoints (newest only) and the final model, so resume keeps it
    eval: EvalSettings = field(default_factory=EvalSettings)  # flags --eval-*
    demo: DemoSettings = field(default_factory=DemoSettings)  # flags --demo-*: the scripted tracker's head start
    smooth: SmoothSettings = field(default_factory=SmoothSettings)  # flags --smooth-*: CAPS action smoothness
    scripted: TrackerGains = field(default_factory=TrackerGains)  # flags --scripted-*: the demonstrations' tracker
    actor_average: NonNegInt = 0  # evaluate and deliver the actor's weights averaged over ~N updates; 0 = live weights
    encoder_checkpoint: FilePath = ""  # the CMVAE of in-process cmvae runs and `swimm up`'s encoders (default: shipped)
    sim_config: FilePath = ""  # a `swimm sim` settings file (noise, scenery): the in-process envs' or `swimm up`'s sim
    step_timeout_s: PosFloat = 2.0  # distributed: wait per try before re-sending a step
    max_retries: NonNegInt = 10  # distributed: re-sends before a step fails naming the missing service
    device: str = "auto"  # torch device of the learner
    threads: NonNegInt = 1  # torch CPU threads; 1 leaves the other cores to the sim and encoder; 0 = torch's default
    log_interval_s: PosFloat = 30.0  # seconds between progress lines in the log
    progress_bar: bool = True  # tqdm bar (only when stderr is a terminal)


def check_sim_config(path: str) -> None:
    """Refuse a ``--sim-config`` that names no file, or a world the sim would refuse, before anything starts."""
    if not path:
        return
    if not Path(path).is_file():
        raise FileNotFoundError(f"--sim-config {path}: no such settings file for the sim")
    try:
        world_of_file(path)
    except SettingsError:
        raise  # it names the file
    except ValueError as exc:
        raise ValueError(f"--sim-config {path}: {exc}") from None


def default_run_dir(settings: LearnCommandSettings) -> Path:
    algo = settings.algo.rsplit(":", 1)[-1].lower()
    return Path("runs") / f"{algo}-{settings.obs}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}"
