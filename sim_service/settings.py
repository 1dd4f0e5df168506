"""Settings of the simulated world, shared by `swimm sim`, `swimm dataset` and in-process use, and of the sim
process that serves worlds (`swimm sim`)."""

from __future__ import annotations

import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from services import settings as settings_mod
from services.settings import NonNegInt, PosFloat, PosInt, ZenohSettings, at_least
from sim_service.latency import LatencySettings
from sim_service.noise import ImageNoise, NoiseSettings
from sim_service.scenery import SceneSettings

Motion = Literal["planar", "3d"]
MOTIONS: tuple[str, ...] = typing.get_args(Motion)
MesaThreads = Annotated[int, at_least(-1)]  # -1: Mesa's own default
MAX_POD_SIZE = 6  # the most dolphins a world holds: the target and its companions


def check_pod(size: int, crossing: bool) -> None:
    """Refuse a pod outside 1 to MAX_POD_SIZE, or a crossing with no companion to cross, naming the flags."""
    if not 1 <= size <= MAX_POD_SIZE:
        raise ValueError(f"--dolphin-pod-size must be 1 to {MAX_POD_SIZE}, got {size}")
    if crossing and size < 2:
        raise ValueError(f"--dolphin-pod-crossing needs a companion to cross: --dolphin-pod-size {size} has none")


@dataclass
class PodSettings:
    """A pod for a world built from a task (the in-process evaluation), under the sim's flags: --dolphin-pod-*."""

    size: int = 1  # dolphins in the world, the target included
    crossing: bool = False  # the crossing split

    def check(self) -> None:
        check_pod(self.size, self.crossing)


@dataclass
class DolphinSettings:
    """How the dolphin swims; simple field types so `services.settings` turns them into ``--dolphin-*`` flags."""

    motion: Motion = "planar"  # planar: the paper's, at one depth; 3d: climbs, dives and surfacing in a depth band
    pod_size: int = 1  # dolphins in the world: the target and pod_size - 1 companions swimming beside it
    pod_crossing: bool = False  # the crossing split: one companion crosses between the rover and the target every 10 s

    def check(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"unknown dolphin motion {self.motion!r}; choose one of {', '.join(MOTIONS)}")
        check_pod(self.pod_size, self.pod_crossing)


@dataclass
class WorldSettings:
    image_size: PosInt = 64  # square RGB frames for the encoder
    render: bool = True  # False: telemetry only (state observations, physics tests)
    render_scale: PosInt = 1  # render at image_size * scale and downscale with OpenCV (anti-aliasing)
    # The process's, not the World's: its entry point sets LP_NUM_THREADS from it (services/process.py).
    render_threads: MesaThreads = 0  # llvmpipe threads (LP_NUM_THREADS): 0 draws on the stepping thread, -1 Mesa picks
    physics_dt: PosFloat = 0.02  # seconds per step: one action per physics step (lock-step)
    noise: NoiseSettings = field(default_factory=NoiseSettings)  # image noise, all off by default (--noise-* flags)
    latency: LatencySettings = field(default_factory=LatencySettings)  # camera and control delays (--latency-* flags)
    scene: SceneSettings = field(
        default_factory=SceneSettings
    )  # the world's scenery, plain by default (--scene-* flags)
    dolphin: DolphinSettings = field(default_factory=DolphinSettings)  # how the target swims (--dolphin-* flags)

    def check(self) -> None:
        """Refuse what building a World would refuse (a noise or scene preset, a range), before any is built."""
        ImageNoise(self.noise)
        self.latency.check()
        self.scene.resolved()
        self.dolphin.check()


@dataclass
class SimSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    world: WorldSettings = field(default_factory=WorldSettings, metadata={"flatten": True})
    train_envs: NonNegInt = 1  # envs of the train channel this sim serves
    eval_envs: NonNegInt = 1  # envs of the eval channel this sim serves
    first_train_env: NonNegInt = 0  # train env ids start here: sims serving one run side by side take disjoint ranges
    realtime: bool = False  # physics keeps running at physics_dt; the last action is held
    ident: str = ""  # this sim's id in liveliness and metrics; default sim-<pid>
    claim_grace_s: float = 10.0  # a claim lapses when its holder's token stays gone this long
    poll_ms: float = 0.0  # poll the inbox this long, then nap (services/polling.py): faster lock-step for a spare core


def world_of_file(path: str | Path) -> WorldSettings:
    """The world a `swimm sim` settings file describes (image noise, scenery, pod), refused as the sim would
    refuse it, for in-process envs."""
    # The file alone: a SWIMM_* variable meant for another command must not reach the world through the sim's names.
    world = settings_mod.load(SimSettings, None, str(path), environ={}).world
    world.check()
    return world
