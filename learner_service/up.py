"""`swimm up`: the whole local system as separate processes: router, sim, encoder(s) and a learner that trains.

    swimm up                                   # SAC on cmvae observations with the shipped CMVAE
    swimm up --obs state --steps 20000         # ground-truth observations: no encoder is started
    swimm up --encoders 2 --envs 8 --group-size 4

Every `swimm learn` flag is a `swimm up` flag too (``--algo``, ``--steps``, ``--eval-*``, ``--run-dir`` ...)
and is handed to the learner through ``<run>/learn.yaml``; ``--connect`` and ``--mode`` are ignored, as every
process joins the router this command starts (on ``--port``, 7447 by default, so `swimm eval --connect
tcp/127.0.0.1:7447` can attach to the sim's spare eval env while training runs) in the ``--topology`` mode:
``peer`` (the default) lets the router introduce the processes, which then send each message directly to one
another, a hop fewer than ``client``, where every message passes through the router.

Start-up is ordered and bounded: the router must listen, then the sim and each encoder must announce
themselves (liveliness) within ``--startup-timeout-s``; a process that dies meanwhile fails the command with
its own log. Then the learner trains with its progress shown here (from ``<run>/progress.json``). When it
ends, or on Ctrl-C / SIGTERM, the learner is stopped first (it saves its model and summary plot), then the
encoders, the sim and the router. The run folder keeps the learner's outputs and every process's log in logs/.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from tqdm.contrib.logging import logging_redirect_tqdm

from encoder_service import DEFAULT_CHECKPOINT, Engine
from learner_service.learn_settings import (
    TASK_DOLPHIN_MOTIONS,
    LearnCommandSettings,
    check_sim_config,
    default_run_dir,
)
from learner_service.progress import (
    BEST_MODEL,
    BEST_MODEL_SCORE,
    EVALUATIONS_CSV,
    FINAL_MODEL,
    LEARN_CONFIG,
    LIVE_MODEL,
    UP_CONFIG,
    PhaseBar,
    describe_progress,
    read_progress,
)
from services import settings as settings_mod
from services.keys import Keys
from services.lifecycle import stop_on_signals
from services.low_latency import check_low_latency_group
from services.presence import Roster
from services.procs import ProcessGroup, Service, zenoh_flags
from services.session import open_session
from services.settings import (
    NonNegFloat,
    NonNegInt,
    PosInt,
    SettingsError,
    ZenohSettings,
    at_least,
    at_most,
    check_ranges,
    to_dict,
)
from sim_service.responder import check as check_sim
from sim_service.settings import SimSettings

log = logging.getLogger(__name__)

WATCH_PERIOD_S = 0.5


@dataclass
class UpSettings:
    learn: LearnCommandSettings = field(default_factory=LearnCommandSettings, metadata={"flatten": True})
    port: Annotated[int, at_least(0), at_most(65535)] = 7447  # the router's TCP port on 127.0.0.1; 0 = any free port
    encoders: PosInt = 1  # encoder processes (cmvae only)
    encoder_engine: Engine = "torch"  # the encoders' CMVAE inference (`swimm encoder --engine`)
    sims: PosInt = 1  # sim processes, the train envs split between them in equal ranges (the eval envs on the first)
    sim_eval_envs: NonNegInt = 2  # eval envs the sim serves: one for the learner's evaluations, one for `swimm eval`
    topology: Literal["peer", "client"] = "peer"  # peer: direct links once the router introduces them; client: via it
    stop_timeout_s: NonNegFloat = 180.0  # how long the learner may take to save after SIGTERM before it is killed
    restart_limit: NonNegInt = 3  # times a router, sim or encoder that dies is restarted before the run ends (saved)
    restart_backoff_s: NonNegFloat = 2.0  # wait before a service's first restart, doubled for each one after


def sim_shares(envs: int, sims: int) -> list[tuple[int, int]]:
    """(first train env, count) of each of ``sims`` sims: equal, contiguous ranges of ids 0..envs-1."""
    if sims < 1 or envs % sims:
        raise ValueError(f"--sims must be >= 1 and divide --envs into equal shares (got {sims} sims, {envs} envs)")
    share = envs // sims
    return [(index * share, share) for index in range(sims)]


def largest_whole_group(share: int, largest: int) -> int:
    """The largest group of at most ``largest`` envs that a sim's ``share`` divides into whole groups."""
    return max(size for size in range(1, min(share, largest) + 1) if share % size == 0)


def group_size_for(envs: int, group_size: int, sims: int, largest_group: int = 0) -> int:
    """The learner's group size: as asked, or one group per sim when several sims serve the envs (a group is
    stepped by one sim, so groups must not straddle two). ``largest_group`` (0: no limit) is the most envs one
    message may carry (a low-latency session's); one group per sim then becomes the largest group that divides
    a sim's share and fits."""
    if sims == 1:
        return group_size
    share = envs // sims
    if group_size == 0:
        return largest_whole_group(share, largest_group or share)
    if share % group_size:
        raise ValueError(
            f"--group-size {group_size} does not divide the {share} envs of each of the {sims} sims: a group "
            "is stepped by one sim, so each sim's share must be whole groups"
        )
    return group_size


class ServiceDied(RuntimeError):
    """A process of the system exited while it was needed; the message carries its log's tail."""


def encoder_checkpoint(learn: LearnCommandSettings) -> Path | None:
    """The CMVAE the encoders load (None when the observation mode needs no encoder); fails clearly if absent."""
    if learn.obs != "cmvae":
        return None
    path = Path(learn.encoder_checkpoint) if learn.encoder_checkpoint else DEFAULT_CHECKPOINT
    if not path.is_file():
        raise FileNotFoundError(
            f"the CMVAE checkpoint {path} does not exist. Train one (`swimm dataset`, then `swimm train-encoder`) "
            f"and pass it with --encoder-checkpoint, or run without an encoder: `swimm up --obs state`"
        )
    return path


def child_commands(settings: UpSettings, endpoint: str, checkpoint: Path | None) -> list[tuple[str, str, list[str]]]:
    """(name, command, arguments) of each sim and encoder `swimm up` starts, joining the router at ``endpoint``:
    what :func:`check` refuses before any starts, and what :meth:`LocalSystem.start_services` starts."""
    zenoh = settings.learn.zenoh
    common = ["--mode", settings.topology, "--connect", endpoint, "--namespace", zenoh.namespace]
    common += zenoh_flags(zenoh.low_latency, zenoh.zenoh_threads)
    config = ["--config", settings.learn.sim_config] if settings.learn.sim_config else []
    shares = sim_shares(settings.learn.envs, settings.sims)
    children = []
    for index, (first, count) in enumerate(shares):
        eval_envs = settings.sim_eval_envs if index == 0 else 0
        sim_args = ["--train-envs", str(count), "--first-train-env", str(first), "--eval-envs", str(eval_envs),
                    "--dolphin-motion", TASK_DOLPHIN_MOTIONS[settings.learn.task]]  # fmt: skip
        if len(shares) > 1:
            sim_args += ["--ident", f"sim-{index}"]
        children.append(("sim" if len(shares) == 1 else f"sim-{index}", "sim", [*common, *sim_args, *config]))
    encoders = settings.encoders if checkpoint is not None else 0
    for index in range(encoders):
        name = "encoder" if encoders == 1 else f"encoder-{index}"
        encoder_args = ["--checkpoint", str(checkpoint), "--ident", f"enc-{index}", "--engine", settings.encoder_engine]
        children.append((name, "encoder", [*common, *encoder_args]))
    return children


def check_port_free(port: int) -> None:
    """Refuse a busy port at once: a router of another run there would otherwise be joined by mistake.

    SO_REUSEADDR lets the probe bind past the TIME_WAIT connections a just-stopped run leaves for a minute
    (the router rebinds past them too), while a live listener still refuses it.
    """
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            raise RuntimeError(
                f"port {port} is in use (another `swimm up` or router?); stop it or pass --port 0 for a free one"
            ) from None


class LocalSystem:
    """The processes of one `swimm up`, started in order and watched until the learner is done."""

    def __init__(self, settings: UpSettings, group: ProcessGroup, run_dir: Path, stop: threading.Event) -> None:
        self.settings = settings
        self.learn = settings.learn
        self.group = group
        self.run_dir = run_dir
        self.stop = stop
        self.namespace = self.learn.zenoh.namespace
        self.wait_s = self.learn.zenoh.startup_timeout_s
        self.restart_due: dict[str, float] = {}  # services that died: when each is started again

    # --- start-up ---------------------------------------------------------------------------------
    def start_services(self, checkpoint: Path | None) -> str:
        """Router, sim and encoders, each waited for; returns the router's endpoint."""
        if self.settings.port:
            check_port_free(self.settings.port)
        zenoh = self.learn.zenoh
        endpoint = self.group.start_router(self.settings.port or None, flags=zenoh_flags(zenoh.low_latency))
        children = child_commands(self.settings, endpoint, checkpoint)
        for name, command, argv in children:
            self.group.start(name, command, *argv)
        watcher = ZenohSettings(connect=[endpoint], namespace=self.namespace, startup_timeout_s=self.wait_s)
        with open_session(watcher, role="up") as session:
            for role in ("sim", "encoder"):
                if count := sum(command == role for _, command, _ in children):
                    self.wait_for_role(session, role, count)
        return endpoint

    def wait_for_role(self, session: Any, role: str, count: int) -> None:
        """Block until ``count`` ``role`` processes announce themselves; fail early if one of ours died."""
        started = time.monotonic()
        next_note = started + 10.0
        with Roster(session, Keys(self.namespace), role) as roster:
            while len(roster.members()) < count:
                self.check_services()
                if self.stop.is_set():
                    raise KeyboardInterrupt
                waited = time.monotonic() - started
                if waited > self.wait_s:
                    raise TimeoutError(
                        f"{role}: {len(roster.members())} of {count} up after {self.wait_s:.0f} s; "
                        f"see {self.group.log_dir}"
                    )
                if time.monotonic() >= next_note:
                    log.info(
                        "waiting for %s (%d of %d up, %.0f s of %.0f s)",
                        role,
                        len(roster.members()),
                        count,
                        waited,
                        self.wait_s,
                    )
                    next_note += 10.0
                time.sleep(0.1)
            log.info("%s up: %s (%.1f s)", role, sorted(roster.members()), time.monotonic() - started)

    def check_services(self, skip: Service | None = None) -> None:
        """Supervise (compose's ``restart: on-failure``): a service that died is started again after a backoff, up to
        ``restart_limit`` times; past that the run ends. The learner bridges the gap by re-sending its step."""
        now = time.monotonic()
        for service in self.group.services:
            if service is skip or service.alive:
                continue
            if service.refused_settings:
                raise ServiceDied(f"{service.name} refused its settings (not restarted); its log ends:\n"
                                  f"{service.log_tail()}")  # fmt: skip
            if service.restarts >= self.settings.restart_limit:
                after = f" after {service.restarts} restarts (--restart-limit)" if service.restarts else ""
                raise ServiceDied(
                    f"{service.name} exited with {service.process.returncode}{after}; its log ends:\n"
                    f"{service.log_tail()}"
                )
            if service.name not in self.restart_due:
                backoff = self.settings.restart_backoff_s * 2**service.restarts
                self.restart_due[service.name] = now + backoff
                log.warning("%s exited with %s; restarting it in %.0f s (restart %d of %d)", service.name,
                            service.process.returncode, backoff, service.restarts + 1,
                            self.settings.restart_limit)  # fmt: skip
            due = self.restart_due[service.name]
            if now >= due:
                del self.restart_due[service.name]
                self.group.restart(service)

    def start_learner(self, endpoint: str) -> Service:
        learn = learner_settings(self.settings, endpoint, self.run_dir)
        config = self.run_dir / LEARN_CONFIG
        config.write_text(yaml.safe_dump(to_dict(learn), sort_keys=False))
        return self.group.start("learner", "learn", "--config", str(config))

    # --- watching -----------------------------------------------------------------------------------
    def watch(self, learner: Service) -> int:
        """Show the learner's progress until it exits, a service dies, or a stop is asked; returns an exit code."""
        interactive = sys.stderr.isatty()
        bar = PhaseBar(disable=not interactive)
        next_line = time.monotonic() + self.learn.log_interval_s
        phase, logged = None, 0  # the phase last shown, and how many of the phases entered have a line
        try:
            with logging_redirect_tqdm():
                while learner.alive:
                    if self.stop.is_set():
                        self.stop_learner(learner)
                        break
                    self.check_services(skip=learner)
                    progress = read_progress(self.run_dir)
                    if progress is not None:
                        bar.show(progress)
                        # No bar: a line at each new phase and every --log-interval-s.
                        entered = progress.get("phases_entered", [])
                        if not interactive:  # a phase begun and ended between two polls still gets its line
                            for missed in entered[logged:-1]:
                                log.info("learner: %s (begun and ended between two looks)", missed)
                        logged = max(logged, len(entered))
                        if not interactive and (progress.get("phase") != phase or time.monotonic() >= next_line):
                            next_line = time.monotonic() + self.learn.log_interval_s
                            phase = progress.get("phase")
                            log.info("learner: %s", describe_progress(progress))
                    self.stop.wait(WATCH_PERIOD_S)
        except ServiceDied:
            self.stop_learner(learner)
            raise
        finally:
            progress = read_progress(self.run_dir)
            if progress is not None:
                bar.show(progress)
            bar.close()
        code = learner.process.wait()
        if code < 0:  # killed by a signal (e.g. SIGTERM before its training loop began): the shell's convention
            code = 128 - code
        if code != 0 and not self.stop.is_set():
            log.error("the learner exited with %d; its log ends:\n%s", code, learner.log_tail())
        return code

    def stop_learner(self, learner: Service) -> None:
        log.info("stopping the learner (up to %.0f s to save)", self.settings.stop_timeout_s)
        self.group.stop(learner, timeout_s=self.settings.stop_timeout_s)


def check(settings: UpSettings) -> UpSettings:
    """Refuse, before any process starts or any folder is made, what this command or any process it would
    start would refuse (each by the command's own check); the settings with the learner's group size resolved."""
    check_ranges(settings)
    learn = settings.learn
    check_sim_config(settings.learn.sim_config)
    largest_group = 0
    if learn.zenoh.low_latency:  # its messages cannot fragment: groups must fit the sim's observations
        image_size = settings_mod.load(SimSettings, None, settings.learn.sim_config or None).world.image_size
        largest_group = check_low_latency_group(learn.group_size, image_size)
    group_size = group_size_for(learn.envs, learn.group_size, settings.sims, largest_group)
    settings = dataclasses.replace(settings, learn=dataclasses.replace(learn, group_size=group_size))
    endpoint = f"tcp/127.0.0.1:{settings.port}"  # its real port is known once the router listens; not checked
    for name, command, argv in child_commands(settings, endpoint, encoder_checkpoint(settings.learn)):
        try:
            check_child(command, argv)
        except (ValueError, FileNotFoundError) as exc:
            raise SettingsError(f"the {name} it would start refuses its settings: {exc}") from None
    from learner_service.command import check as check_learner  # stable-baselines3: only once the rest passed
    from learner_service.command import check_run_dir

    check_learner(learner_settings(settings, endpoint, Path(".")))
    check_run_dir(learn.run_dir, learn.resume)  # the learner it starts would refuse it, after the services started
    return settings


def check_child(command: str, argv: list[str]) -> None:
    """Refuse a sim's or an encoder's arguments as `swimm sim` or `swimm encoder` would refuse them."""
    if command == "sim":
        check_sim(settings_mod.from_command_line(SimSettings, argv))
    else:  # an encoder: its settings load and pass its check as its command's do, or are refused
        from encoder_service.service import EncoderSettings  # torch: not for `swimm up --help`
        from encoder_service.service import check as check_encoder

        check_encoder(settings_mod.from_command_line(EncoderSettings, argv))


def learner_settings(settings: UpSettings, endpoint: str, run_dir: Path) -> LearnCommandSettings:
    """What the learner `swimm up` starts is given: the router's endpoint, the run folder, no bar of its own."""
    learn = settings.learn
    return dataclasses.replace(
        learn,
        zenoh=dataclasses.replace(learn.zenoh, mode=settings.topology, connect=[endpoint]),
        run_dir=str(run_dir),
        backend="zenoh",
        sim_config="",  # the sim it starts reads the file
        progress_bar=False,  # this command draws the bar
    )


def run(settings: UpSettings) -> int:
    if settings.learn.backend != "zenoh":
        log.info("swimm up always trains through the services; --backend %s is ignored", settings.learn.backend)
    settings = check(settings)
    learn = settings.learn
    checkpoint = encoder_checkpoint(learn)
    run_dir = Path(learn.run_dir) if learn.run_dir else default_run_dir(learn)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_up_config(settings, run_dir)
    stop = threading.Event()
    started = time.monotonic()
    on_signal = stop_on_signals(stop, "stopping the learner (it saves), then the services")
    with on_signal, ProcessGroup(run_dir / "logs") as group:
        system = LocalSystem(settings, group, run_dir, stop)
        try:
            endpoint = system.start_services(checkpoint)
        except KeyboardInterrupt:
            log.info("stopped during start-up")
            return 130
        log.info(
            "router at %s, namespace %s, processes joined as %ss; training %s on %s, run folder %s",
            endpoint,
            system.namespace,
            settings.topology,
            learn.algo,
            learn.obs,
            run_dir,
        )
        code = system.watch(system.start_learner(endpoint))
    log.info(
        "all processes stopped after %.0f s; run folder %s (logs in %s)",
        time.monotonic() - started,
        run_dir,
        run_dir / "logs",
    )
    if (run_dir / FINAL_MODEL).is_file():  # finished or stopped: the learner saved before it exited
        sys.stdout.write(what_the_run_saved(run_dir, learn))
    return code


def what_the_run_saved(run_dir: Path, learn: LearnCommandSettings) -> str:
    """What a finished or stopped run leaves a user: every model file it saved, the command that evaluates the
    policy, and the one that resumes training with this run's settings."""
    from learner_service.checkpoints import replay_buffer_path  # stable-baselines3: not for `swimm up --help`

    lines = [f"saved in {run_dir}:"]
    final = run_dir / FINAL_MODEL
    buffer = replay_buffer_path(final)
    with_buffer = f" (+ {buffer.name}, its replay buffer)" if buffer.is_file() else ""
    lines.append(f"  {final.name}{with_buffer}: the model as training ended")
    if (run_dir / LIVE_MODEL).is_file():
        lines.append(f"  {LIVE_MODEL}: the actor's own weights then, not averaged (what --resume takes)")
    score_path = run_dir / BEST_MODEL_SCORE
    if score_path.is_file():
        score = json.loads(score_path.read_text())
        lines.append(f"  {BEST_MODEL}: the best evaluated policy, return {score['mean_return']:.0f} at "
                     f"{score['num_timesteps']} steps (scored in {BEST_MODEL_SCORE}, {EVALUATIONS_CSV})")  # fmt: skip
    checkpoints = sorted((run_dir / "checkpoints").glob("model_*_steps.zip"), key=lambda path: path.stat().st_mtime)
    if checkpoints:
        lines.append(f"  checkpoints/{checkpoints[-1].name}: the newest of {len(checkpoints)} checkpoints")
    lines.append("  summary.png, train*.monitor.csv, tensorboard/ and logs/: how training went")
    policy = run_dir / (BEST_MODEL if score_path.is_file() else FINAL_MODEL)
    evaluate = f"swimm eval --backend inprocess --algo {learn.algo} --obs {learn.obs} --checkpoint {policy}"
    if learn.obs == "cmvae" and learn.encoder_checkpoint:
        evaluate += f" --encoder-checkpoint {learn.encoder_checkpoint}"
    if learn.task != "planar":  # the default: planar runs' command stays as it always read
        evaluate += f" --task {learn.task}"
    if learn.sim_config:  # the world it trained in: a pod, a noise, a scenery
        evaluate += f" --sim-config {learn.sim_config}"
    resume_from = run_dir / (LIVE_MODEL if (run_dir / LIVE_MODEL).is_file() else FINAL_MODEL)
    lines.append(f"evaluate the policy: {evaluate} --episodes 20 --seed 127")
    lines.append(f"resume training: swimm up --config {run_dir / UP_CONFIG} --resume {resume_from}")
    return "\n".join(lines) + "\n"


def write_up_config(settings: UpSettings, run_dir: Path) -> None:
    """This run's settings, its folder included, as a `swimm up --config` file: what resumes it as it was."""
    learn = dataclasses.replace(settings.learn, run_dir=str(run_dir), resume="")
    data = to_dict(dataclasses.replace(settings, learn=learn))
    (run_dir / UP_CONFIG).write_text(yaml.safe_dump(data, sort_keys=False))
