"""Training benchmark: SB3 env-steps/s through the distributed pipeline vs the same training in one process.

Both halves train the same algorithm with its shipped settings (``learner_service/hyperparams/<algo>.yaml``), the
same seed and cmvae observations for the same number of steps, in one invocation:

- in-process: a TrackingEnv (World + LatentEncoder in the learner's process);
- distributed: `swimm router`, `swimm sim` and `swimm encoder` as separate processes, the learner stepping a
  ProxyVecEnv, so every step is action -> sim -> encoder -> learner. With ``mode="peer"`` (the default, what
  `swimm up` runs) the processes join as Zenoh peers and each hop goes directly from one to the next, the router
  only introducing them; with ``mode="client"`` (what deploy/docker-compose.yml runs) every hop passes through
  the router.

Since the ProxyEnv reproduces the in-process env bit for bit, the two runs see the same episodes and do the same
gradient steps: the ratio isolates the cost of the transport and the process hops. The rate counts every
env step of ``model.learn`` including the gradient steps between episodes (end to end), excluding only the
start of the processes and the building of the model.

CPU threads: torch runs with one thread in the learner and in the encoder. In lock step only one process
works at a time, and the idle-spinning threads of a two-thread torch pool steal the core the next process in
the chain needs (docs/benchmarks.md, one torch thread in the training benchmark).
"""

from __future__ import annotations

import contextlib
import cProfile
import logging
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
from stable_baselines3.common.callbacks import BaseCallback

import learner_service
from bench.layout import default_layout
from encoder_service.inference import DEFAULT_CHECKPOINT, LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint
from learner_service.checkpoints import load_for_resume
from learner_service.envs import make_vec_env
from learner_service.proxy_env import ProxySettings
from learner_service.registry import make_model, training_callbacks
from learner_service.task import TaskSettings
from learner_service.up import sim_shares
from services.procs import ProcessGroup, zenoh_flags
from services.settings import ZenohSettings

log = logging.getLogger(__name__)

NAMESPACE = "swimm/bench-train"
SEED = 97  # the SPEC's first training seed
TORCH_THREADS = 1  # see the module docstring
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
SCRATCH_STEPS = 1500  # from scratch, one env: about 30 of the first, short, episodes
SCRATCH_VEC_STEPS = 4000  # from scratch, several envs: as short episodes, and the first vector steps are a start-up
STEADY_EPISODES = 2  # from a trained policy: full-length episodes per env, each ending with its gradient steps


def encoder_checkpoint(folder: Path) -> Path:
    """The shipped CMVAE, or an untrained one of the same shape (encoding costs the same whatever the weights)."""
    if DEFAULT_CHECKPOINT.is_file():
        return DEFAULT_CHECKPOINT
    log.warning("no shipped CMVAE at %s; timing an untrained one of the same architecture", DEFAULT_CHECKPOINT)
    torch.manual_seed(0)
    path = folder / "untrained-cmvae.pt"
    torch.save(make_checkpoint(CMVAE(), beta=8.0, epoch=0, val_loss=float("nan"), metrics={}), path)
    return path


class RolloutClock(BaseCallback):
    """Wall time spent collecting rollouts (env steps and the policy's actions), the rest of learn() being training."""

    def __init__(self) -> None:
        super().__init__()
        self.rollout_s = 0.0
        self._started = 0.0

    def _on_rollout_start(self) -> None:
        self._started = time.perf_counter()

    def _on_rollout_end(self) -> None:
        self.rollout_s += time.perf_counter() - self._started

    def _on_step(self) -> bool:
        return True


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds a process (all its threads) has used so far, from Linux's /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


#: The steady state's policy: the clean-frame SAC, whose encoder (cmvae.pt) is the one the bench's encoders run, so
#: its episodes are as long as a tracking policy makes them; kept across the policy to fly's changes so that
#: benchmark numbers stay comparable (docs/benchmarks.md).
STEADY_STATE_POLICY = Path(learner_service.__file__).parent / "models" / "sac_cmvae.zip"


def starting_policy(algo: str, policy: str) -> Path | None:
    """What both halves train on from: ``"auto"`` is :data:`STEADY_STATE_POLICY` for ``sac`` (steady state: episodes
    as long as a tracking policy makes them, as in most of a run, not the first minutes' short ones) and a new model
    for other algorithms; ``"scratch"`` a new model; anything else a saved model of ``algo``."""
    if policy == "scratch" or (policy == "auto" and (algo != "sac" or not STEADY_STATE_POLICY.is_file())):
        return None
    path = STEADY_STATE_POLICY if policy == "auto" else Path(policy)
    if not path.is_file():
        raise FileNotFoundError(f"--policy {path}: no such saved model (or use --policy scratch)")
    return path


def default_steps(envs: int, start: Path | None) -> int:
    """Steps per half: from scratch, the first episodes; from a policy, :data:`STEADY_EPISODES` full episodes of
    every env."""
    if start is None:
        return SCRATCH_STEPS if envs == 1 else SCRATCH_VEC_STEPS
    return STEADY_EPISODES * TaskSettings().max_steps * envs


@dataclass(frozen=True)
class TrainingRun:
    steps: int
    seconds: float
    rollout_seconds: float
    episodes: list[tuple[float, int]]  # (return, length) of each finished episode, from the VecMonitor
    cpu_ms_per_step: dict[str, float]  # per process: where the time goes, robust to other load on the machine

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds

    @property
    def rollout_steps_per_s(self) -> float:
        return self.steps / self.rollout_seconds


def train(
    algo: str, vec_env, steps: int, services: dict[str, int], policy: Path | None = None, profile: str = ""
) -> TrainingRun:
    """Time ``model.learn(steps)`` of a new model, or of ``policy`` trained on, and the CPU it costs the learner and
    the ``services`` (name: pid); ``profile``: a file to write a cProfile of the learner's ``learn`` (CPU time, so
    other processes' load does not inflate it), for ``python -m pstats`` or snakeviz.

    SAC trains per episode (on several envs through learner_service/episodic.py), so it may run a little past
    ``steps``.
    """
    overrides = {"device": "cpu", "verbose": 0, "stats_window_size": 10**6}
    if policy is None:
        model = make_model(algo, vec_env, seed=SEED, overrides=overrides)
    else:
        model = load_for_resume(algo, policy, vec_env, device="cpu", overrides=overrides, verbose=0)
        model.set_random_seed(SEED)
    clock = RolloutClock()
    callbacks = [clock, *training_callbacks(algo, overrides, vec_env.num_envs)]
    cpu_before = {name: process_cpu_s(pid) for name, pid in services.items()}
    profiler = cProfile.Profile(time.process_time) if profile else None
    learner_cpu, started = time.process_time(), time.perf_counter()
    with profiler or contextlib.nullcontext():
        model.learn(total_timesteps=steps, callback=callbacks)
    elapsed, learner_cpu = time.perf_counter() - started, time.process_time() - learner_cpu
    if profiler is not None:
        profiler.dump_stats(profile)
        log.info("the learner's profile is in %s (python -m pstats %s)", profile, profile)
    cpu = {"learner": learner_cpu} | {name: process_cpu_s(pid) - cpu_before[name] for name, pid in services.items()}
    episodes = [(round(float(info["r"]), 4), int(info["l"])) for info in model.ep_info_buffer]
    cpu_ms = {name: round(seconds * 1e3 / model.num_timesteps, 3) for name, seconds in cpu.items()}
    return TrainingRun(model.num_timesteps, elapsed, clock.rollout_s, episodes, cpu_ms)


def inprocess_run(algo: str, steps: int, start: Path | None, checkpoint: Path, engine: str) -> TrainingRun:
    """The in-process half: one TrackingEnv with its own CMVAE, the serial loop a user would otherwise write."""
    task = TaskSettings(obs="cmvae")
    env = make_vec_env("inprocess", task, base_seed=SEED, encoder=LatentEncoder(checkpoint, engine=engine))
    try:
        return train(algo, env, steps, services={}, policy=start)
    finally:
        env.close()


def _inprocess_rollout_rate(algo: str, steps: int, start: Path | None, checkpoint: Path, engine: str) -> float:
    """:func:`inprocess_run` in a worker process of its own: its rollout rate."""
    torch.set_num_threads(TORCH_THREADS)
    return inprocess_run(algo, steps, start, checkpoint, engine).rollout_steps_per_s


def two_inprocess_at_once(algo: str, steps: int, start: Path | None, checkpoint: Path, engine: str) -> float:
    """The in-process half in two processes at the same time: their rollout rates summed.

    Nothing passes between the two, so this is what two cores give the serial loop: the ceiling of a rollout
    ratio on this machine, against which the pipeline's hops and idle time show as the gap.
    """
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        runs = [pool.submit(_inprocess_rollout_rate, algo, steps, start, checkpoint, engine) for _ in range(2)]
        return sum(run.result() for run in runs)


def run(
    steps: int = 0,
    algo: str = "sac",
    mode: str = "peer",
    low_latency: bool = False,
    zenoh_threads: int = 1,
    envs: int = 1,
    group_size: int = -1,
    sims: int = 0,
    encoders: int = 1,
    policy: str = "auto",
    engine: str = "torch",
    profile: str = "",
    ceiling: bool = False,
) -> dict:
    """``steps`` 0: :func:`default_steps`; ``zenoh_threads``: the sims', encoders' and learner's (the learner's
    unless its first Zenoh session is already open; the router keeps its own); ``sims`` 0 and ``group_size`` -1:
    :func:`default_layout`; ``policy``: see :func:`starting_policy`; ``engine``: the CMVAE's inference engine, the
    same in both halves; ``profile``: a file for the cProfile of the distributed half's learner (see
    :func:`train`), empty for none; ``ceiling``: also time :func:`two_inprocess_at_once` (the ``ceiling_*``
    keys)."""
    sims, group_size = default_layout(envs, sims, group_size, low_latency)
    start = starting_policy(algo, policy)
    steps = steps or default_steps(envs, start)
    torch.set_num_threads(TORCH_THREADS)
    task = TaskSettings(obs="cmvae")
    with tempfile.TemporaryDirectory(prefix="swimm-bench-train-") as tmp, ProcessGroup(Path(tmp) / "logs") as group:
        checkpoint = encoder_checkpoint(Path(tmp))
        endpoint = group.start_router(flags=zenoh_flags(low_latency))
        common = ("--mode", mode, "--connect", endpoint, "--namespace", NAMESPACE,
                  *zenoh_flags(low_latency, zenoh_threads))  # fmt: skip
        for index, (first, count) in enumerate(sim_shares(envs, sims)):
            group.start(f"sim-{index}", "sim", *common, "--train-envs", str(count), "--first-train-env", str(first),
                        "--eval-envs", "0", "--ident", f"sim-{index}")  # fmt: skip
        for index in range(encoders):  # named as `swimm up` names them: "encoder" when there is one
            name = "encoder" if encoders == 1 else f"encoder-{index}"
            group.start(name, "encoder", *common, "--checkpoint", str(checkpoint), "--threads", str(TORCH_THREADS),
                        "--engine", engine, "--ident", name)  # fmt: skip
        zenoh = ZenohSettings(
            mode=mode, connect=[endpoint], namespace=NAMESPACE, low_latency=low_latency, zenoh_threads=zenoh_threads
        )
        proxy = ProxySettings(zenoh=zenoh, group_size=group_size)
        # Built first: it waits (bounded) for the sim and the encoder, so they are idle while the in-process half runs.
        distributed_env = make_vec_env("zenoh", task, proxy, n_envs=envs, base_seed=SEED)
        try:
            inprocess = inprocess_run(algo, steps, start, checkpoint, engine)
            pair = two_inprocess_at_once(algo, steps, start, checkpoint, engine) if ceiling else None
            pids = {s.name: s.process.pid for s in group.services}
            distributed = train(algo, distributed_env, steps, pids, policy=start, profile=profile)
        finally:
            distributed_env.close()
        group.check_alive()
    rollout_ratio = distributed.rollout_steps_per_s / inprocess.rollout_steps_per_s
    return {
        "algo": algo,
        "envs": envs,
        "engine": engine,
        "start": "scratch" if start is None else str(start),
        "sims": sims,
        "encoders": encoders,
        "group_size": group_size,
        "topology": mode,
        "transport": "low-latency" if low_latency else "standard",
        "zenoh_threads": zenoh_threads,
        "inprocess_steps_per_s": round(inprocess.steps_per_s, 1),
        "distributed_steps_per_s": round(distributed.steps_per_s, 1),
        "ratio": round(distributed.steps_per_s / inprocess.steps_per_s, 3),
        # The same rates over the rollouts alone (env steps and actions, without the gradient steps between them).
        "inprocess_rollout_steps_per_s": round(inprocess.rollout_steps_per_s, 1),
        "distributed_rollout_steps_per_s": round(distributed.rollout_steps_per_s, 1),
        "rollout_ratio": round(rollout_ratio, 3),
        "training_share": round(1 - distributed.rollout_seconds / distributed.seconds, 3),  # of the distributed run
        **(ceiling_keys(pair, inprocess.rollout_steps_per_s, rollout_ratio) if pair is not None else {}),
        # CPU milliseconds per env step of each process over the whole run (the learner's includes its training).
        "inprocess_cpu_ms_per_step": inprocess.cpu_ms_per_step["learner"],
        "distributed_cpu_ms_per_step": distributed.cpu_ms_per_step,
        "steps": distributed.steps,
        "episodes": len(distributed.episodes),
        # The same seed gave the same training run (one env only: several envs play other episodes).
        **({"same_episodes": distributed.episodes == inprocess.episodes} if envs == 1 else {}),
    }


def ceiling_keys(pair_rollout_steps_per_s: float, inprocess_rollout_steps_per_s: float, rollout_ratio: float) -> dict:
    """Two in-process loops at once against one (``ceiling_ratio``: the most a rollout ratio could be here), and
    the share of it the pipeline's ``rollout_ratio`` reached."""
    ceiling = pair_rollout_steps_per_s / inprocess_rollout_steps_per_s
    return {
        "ceiling_rollout_steps_per_s": round(pair_rollout_steps_per_s, 1),
        "ceiling_ratio": round(ceiling, 3),
        "share_of_ceiling": round(rollout_ratio / ceiling, 3),
    }
