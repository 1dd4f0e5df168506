"""`swimm learn`: train a learner on the tracking task, distributed (Zenoh) or in-process, into a run folder.

    swimm learn --algo sac --obs cmvae --steps 200000 --envs 4 --seed 97 \\
        --connect tcp/127.0.0.1:7447 --namespace swimm/default --run-dir runs/sac --backend zenoh

The run folder holds everything a run leaves (see docs/learner.md): ``settings.json`` (what was asked and what
was resolved), ``train.monitor.csv`` (one row per training episode with its ending), ``tensorboard/``,
``checkpoints/``, ``best_model.zip`` + ``best_model.json`` + ``evaluations.csv`` (evaluation callback),
``final_model.zip`` (+ its replay buffer), ``progress.json`` (live numbers), ``result.json`` (the run's
totals) and ``summary.png`` (reward per episode and how episodes ended).

SIGTERM or Ctrl-C ends training at the next step; the model, the plot and the totals are still written.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import threading
import time
from contextlib import ExitStack, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch
import yaml
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.utils import configure_logger
from tqdm.contrib.logging import logging_redirect_tqdm

from encoder_service import DEFAULT_CHECKPOINT
from learner_service.averaging import ActorAverage
from learner_service.callbacks import (
    EVALUATIONS_CSV,
    CheckpointCallback,
    EpisodeStatsCallback,
    RolloutEvalCallback,
    StopOnEvent,
    WallClockLimit,
)
from learner_service.checkpoints import load_for_resume, save_model
from learner_service.demonstrations import demonstrate, resume_cloning
from learner_service.envs import check_backend, make_env, make_vec_env, shared_encoder
from learner_service.episodic import episodic_schedule
from learner_service.identity import check_task, encoder_for, policy_identity, stamp
from learner_service.learn_settings import LearnCommandSettings, check_sim_config, default_run_dir
from learner_service.live_encoders import require_live_encoders
from learner_service.plots import plot_training, read_monitor
from learner_service.progress import (
    FINAL_MODEL,
    LIVE_MODEL,
    PROGRESS_FILE,
    PhaseBar,
    RunProgress,
    latest_evaluation,
)
from learner_service.registry import (
    LATENT_SCRIPTED,
    SCRIPTED_NAMES,
    load_hyperparams,
    load_policy,
    make_model,
    merge_overrides,
    resolve_algorithm,
    training_callbacks,
)
from learner_service.smoothness import keep_smooth
from learner_service.task import TaskSettings
from services.keys import Keys
from services.lifecycle import stop_on_signals
from services.results import refuse_held_folder
from services.settings import check_ranges, to_dict
from sim_service.settings import world_of_file

log = logging.getLogger(__name__)

DEFAULT_STEPS = 1_000_000  # the SPEC's training length, for algorithms without a YAML of their own
MONITOR_NAME = "train"  # VecMonitor writes train.monitor.csv (train-2.monitor.csv for a resumed run's next part)
SETTINGS_FILE = "settings.json"
RESULT_FILE = "result.json"
SUMMARY_PLOT = "summary.png"


@dataclass
class RunResult:
    """What `swimm learn` measured; written to result.json."""

    num_timesteps: int
    trained_steps: int
    wall_s: float
    env_steps_per_s: float
    episodes: int
    endings: dict[str, int]
    stopped_early: bool
    best_mean_return: float | None


def resolve_steps(settings: LearnCommandSettings) -> int:
    if settings.steps > 0:
        return settings.steps
    if ":" in settings.algo:
        return DEFAULT_STEPS
    return int(load_hyperparams(settings.algo).get("n_timesteps", DEFAULT_STEPS))


def parse_hyperparams(text: str) -> dict[str, Any]:
    """``--hyperparams``: a YAML mapping given inline or as a file path."""
    if not text:
        return {}
    path = Path(text)
    try:
        is_file = path.is_file()
    except OSError:  # an inline mapping longer than a file name may be (a recipe's block of hyperparameters)
        is_file = False
    try:
        loaded = yaml.safe_load(path.read_text() if is_file else text)
    except yaml.YAMLError as exc:
        where = f"file {text}" if is_file else repr(text)
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ValueError(f"--hyperparams {where} is not YAML: {getattr(exc, 'problem', None) or exc}{at}") from None
    if not isinstance(loaded, dict):
        raise ValueError(f"--hyperparams must be a YAML mapping (inline or a file), got {text!r}")
    return loaded


def check(settings: LearnCommandSettings) -> None:
    """Refuse what could only fail later, before anything is started."""
    check_ranges(settings)  # every range, named by its flag (--eval-episodes, not the nested check's --episodes)
    check_backend(settings.backend)
    if settings.algo in SCRIPTED_NAMES:
        raise ValueError(f"a scripted baseline has nothing to learn; evaluate it: `swimm eval --algo {settings.algo}`")
    if settings.demo.teacher not in SCRIPTED_NAMES:
        raise ValueError(f"demo teacher must be one of {', '.join(SCRIPTED_NAMES)}, got {settings.demo.teacher!r}")
    if settings.demo.steps and settings.demo.teacher == LATENT_SCRIPTED and settings.obs != "cmvae":
        raise ValueError(f"demo teacher {LATENT_SCRIPTED} reads the latent: it needs --obs cmvae, got {settings.obs}")
    algorithm, defaults = resolve_algorithm(settings.algo)
    if settings.smooth.enabled and not issubclass(algorithm, OffPolicyAlgorithm | OnPolicyAlgorithm):
        raise ValueError(f"--smooth-* needs a stable-baselines3 off-policy or on-policy learner; {settings.algo} "
                         f"({algorithm.__name__}) is neither")  # fmt: skip
    episodic_schedule(merge_overrides(defaults, parse_hyperparams(settings.hyperparams)), settings.envs)  # refuses -1
    if settings.resume and not Path(settings.resume).is_file():
        raise FileNotFoundError(f"cannot resume: {settings.resume} does not exist")
    if settings.sim_config and settings.backend == "zenoh":
        raise ValueError(
            f"--sim-config {settings.sim_config}: a running sim serves its own world; start it with `swimm sim "
            "--config FILE`, train in process (--backend inprocess), or let `swimm up --sim-config` start the sim"
        )
    check_sim_config(settings.sim_config)


class Training:
    """One run of `swimm learn`: envs, model and callbacks built from the settings, trained, saved, summarised."""

    def __init__(self, settings: LearnCommandSettings, stop: threading.Event | None = None) -> None:
        check(settings)
        self.settings = settings
        self.run_dir = Path(settings.run_dir) if settings.run_dir else default_run_dir(settings)
        self.steps = resolve_steps(settings)
        self.overrides = parse_hyperparams(settings.hyperparams)
        self.stop = stop or threading.Event()
        self.progress = RunProgress()  # the run's phase and numbers; `run` gives it its file, bar and publisher
        self.task = TaskSettings(
            obs=settings.obs, reward=settings.reward, task=settings.task, max_steps=settings.max_steps
        )
        self.eval_task = dataclasses.replace(self.task, max_steps=settings.eval.max_steps, early_termination=False)

    def proxy_settings(self, channel: str) -> Any:
        from learner_service.proxy_env import ProxySettings  # zenoh only for the distributed backend

        return ProxySettings(
            zenoh=self.settings.zenoh,
            channel=channel,
            envs=("0",),
            step_timeout_s=self.settings.step_timeout_s,
            max_retries=self.settings.max_retries,
            role="learner",
            group_size=self.settings.group_size if channel == "train" else 0,
        )

    def run(self) -> RunResult:
        s = self.settings
        self.run_dir.mkdir(parents=True, exist_ok=True)
        log.info(
            "run folder %s: %s %s, %d steps on %d %s env(s)", self.run_dir, s.algo, s.obs, self.steps, s.envs, s.backend
        )
        with ExitStack() as stack:
            bar = PhaseBar(disable=not (s.progress_bar and sys.stderr.isatty()))
            stack.callback(bar.close)
            self.progress = RunProgress(self.run_dir / PROGRESS_FILE, self.steps, bar=bar)
            if (evaluation := latest_evaluation(self.run_dir)) is not None:  # a resumed run's
                self.progress.evaluated(*evaluation)
            session = None
            if s.backend == "zenoh":
                from services.metrics import MetricsPublisher  # zenoh only for the distributed backend
                from services.presence import process_ident
                from services.session import open_session

                session = stack.enter_context(open_session(s.zenoh, role="learner"))
                if s.obs == "cmvae":  # its latents must come from the CMVAE its models will record
                    encoder = s.encoder_checkpoint or DEFAULT_CHECKPOINT
                    reader = f"this run (--encoder-checkpoint {encoder})"
                    require_live_encoders(session, Keys(s.zenoh.namespace), encoder, reader, s.zenoh.startup_timeout_s)
                # `swimm status` shows the phase, steps and latest evaluation of each learner process.
                stack.enter_context(MetricsPublisher(session, Keys(s.zenoh.namespace), "learner",
                                                     process_ident("learner"), self.progress))  # fmt: skip
            encoder = (
                shared_encoder(self.task, checkpoint=s.encoder_checkpoint or None) if s.backend == "inprocess" else None
            )
            world = self.inprocess_world()
            train_proxy = self.proxy_settings("train") if session is not None else None
            env = make_vec_env(
                s.backend,
                self.task,
                train_proxy,
                s.envs,
                s.seed,
                monitor_path=self.next_monitor_path(),
                encoder=encoder,
                session=session,
                world=world,
            )
            stack.callback(env.close)
            eval_env = None
            if s.eval.enabled:
                eval_proxy = self.proxy_settings("eval") if session is not None else None
                eval_env = make_env(
                    s.backend,
                    self.eval_task,
                    eval_proxy,
                    s.eval.env,
                    s.eval.seed,
                    encoder=encoder,
                    session=session,
                    world=world,
                )
                stack.callback(eval_env.close)
            # Only now does the folder hold a run (check_run_dir): a start that failed before leaves it free to retry.
            self.write_settings()
            return self.train(env, eval_env)

    def inprocess_world(self) -> Any:
        """The world of in-process envs from ``--sim-config`` (as a sim started with it would serve), else None."""
        return world_of_file(self.settings.sim_config) if self.settings.sim_config else None

    def build_model(self, env: Any) -> Any:
        s = self.settings
        if s.threads > 0:
            torch.set_num_threads(s.threads)
        tensorboard = str(self.run_dir / "tensorboard")
        if s.resume:
            return load_for_resume(
                s.algo, s.resume, env, device=s.device, overrides=self.overrides, tensorboard_log=tensorboard
            )
        return make_model(
            s.algo, env, s.seed, overrides=self.overrides | {"device": s.device}, tensorboard_log=tensorboard
        )

    def identity(self) -> dict[str, Any]:
        """What every saved model records: its task and the encoder its latents came from (learner_service.identity).

        A resumed run must go on with the task and the encoder it started on; others are refused before training.
        """
        s = self.settings
        encoder = s.encoder_checkpoint or DEFAULT_CHECKPOINT
        if s.resume:
            check_task(s.resume, s.task)
        if s.resume and s.obs == "cmvae":
            encoder_for(s.resume, encoder)  # refuses an encoder other than the one the run started on
        return policy_identity(encoder, s.obs, s.reward, s.task)

    def train(self, env: Any, eval_env: Any) -> RunResult:
        s = self.settings
        clock = time.perf_counter()  # the budget and the evaluations' wall_s count the demonstrations too
        identity = self.identity()  # first: a resumed model of another task would fail to load with a vaguer error
        model = self.build_model(env)
        stamp(model, identity)
        tb_log_name = s.algo.rsplit(":", 1)[-1].upper()
        # The run's logger now rather than inside learn(): the demonstrations' critic warm-up records its losses too.
        model.set_logger(configure_logger(model.verbose, model.tensorboard_log, tb_log_name, not s.resume))
        if s.demo.steps:
            if s.resume:
                resume_cloning(model, s.demo, s.seed, Path(s.resume), self.run_dir)
            else:
                teacher = load_policy(s.demo.teacher, s.encoder_checkpoint or None, gains=s.scripted)
                demonstrate(model, env, s.demo, s.seed, self.run_dir, teacher, self.progress)
        if s.smooth.enabled:
            keep_smooth(model, s.smooth, s.seed)
            log.info("actor updates keep CAPS smoothness terms: %s", s.smooth)
        average = None
        if s.actor_average:
            average = ActorAverage(model, s.actor_average)
            log.info("evaluations and the final model average the actor over ~%d updates", s.actor_average)
        acting = average.swapped_in if average is not None else nullcontext  # the weights evaluations and saves use
        start_steps = model.num_timesteps
        stats = EpisodeStatsCallback(start_steps + self.steps, s.log_interval_s, self.progress)
        callbacks = [stats, *training_callbacks(s.algo, self.overrides, s.envs)]
        evaluation = None
        if eval_env is not None:
            evaluation = RolloutEvalCallback(eval_env, s.eval, self.run_dir, started=clock, acting=acting,
                                             progress=self.progress)  # fmt: skip
            callbacks.append(evaluation)
        if s.budget_min:
            callbacks.append(WallClockLimit(s.budget_min * 60, clock))
        if s.checkpoint_every:
            callbacks.append(
                CheckpointCallback(s.checkpoint_every, self.run_dir / "checkpoints", s.envs, s.save_replay_buffer)
            )
        callbacks.append(StopOnEvent(self.stop))
        started = time.perf_counter()
        try:
            on_signal = stop_on_signals(
                self.stop, "finishing the current step, then saving", second_ctrl_c_interrupts=True
            )
            with on_signal, logging_redirect_tqdm():  # log lines above the bar, not through it
                model.learn(
                    self.steps,
                    callback=callbacks,
                    reset_num_timesteps=not s.resume,
                    tb_log_name=tb_log_name,
                )
        finally:
            if average is not None:
                save_model(model, self.run_dir / LIVE_MODEL, replay_buffer=False)
            with acting():
                save_model(model, self.run_dir / FINAL_MODEL, s.save_replay_buffer)
            self.plot_summary()
        wall = time.perf_counter() - started
        best = evaluation.best_mean_return if evaluation is not None and evaluation.evaluations else None
        result = RunResult(
            num_timesteps=int(model.num_timesteps),
            trained_steps=int(model.num_timesteps - start_steps),
            wall_s=round(wall, 2),
            env_steps_per_s=round((model.num_timesteps - start_steps) / wall, 2),
            episodes=stats.episodes,
            endings=dict(stats.endings),
            stopped_early=self.stop.is_set(),
            best_mean_return=best,
        )
        (self.run_dir / RESULT_FILE).write_text(json.dumps(dataclasses.asdict(result), indent=1))
        log.info(
            "trained %d steps in %.1f s (%.1f env-steps/s), %d episodes, endings %s; run folder %s",
            result.trained_steps,
            wall,
            result.env_steps_per_s,
            result.episodes,
            result.endings,
            self.run_dir,
        )
        return result

    def next_monitor_path(self) -> Path:
        """train, then train-2, train-3... so a run resumed in the same folder keeps the earlier episodes."""
        part = 1 + len(self.monitor_files())
        return self.run_dir / (MONITOR_NAME if part == 1 else f"{MONITOR_NAME}-{part}")

    def monitor_files(self) -> list[Path]:
        return sorted(self.run_dir.glob(f"{MONITOR_NAME}*.monitor.csv"))

    def write_settings(self) -> None:
        resolved = {"run_dir": str(self.run_dir), "steps": self.steps, "hyperparams": self.overrides}
        data = {"settings": to_dict(self.settings), "resolved": resolved, "argv": sys.argv}
        (self.run_dir / SETTINGS_FILE).write_text(json.dumps(data, indent=1, default=str))

    def plot_summary(self) -> None:
        """summary.png from the monitor CSV; a run that finished no episode has nothing to plot (logged)."""
        monitors = self.monitor_files()
        try:
            episodes = read_monitor(monitors)
        except (OSError, ValueError) as exc:
            log.warning("no summary plot: cannot read the monitor files %s (%s)", monitors, exc)
            return
        if episodes.empty:
            log.warning("no summary plot: no training episode finished")
            return
        evaluations_csv = self.run_dir / EVALUATIONS_CSV
        evaluations = pd.read_csv(evaluations_csv) if evaluations_csv.is_file() else None
        plot_training(episodes, self.run_dir / SUMMARY_PLOT, evaluations=evaluations)


def check_run_dir(run_dir: str, resume: str) -> None:
    """Refuse to start a new run in a folder that holds one (its settings.json), whose files it would overwrite."""
    if run_dir and not resume:
        remedy = "--resume one of its models to go on with it, or choose another --run-dir for a new one"
        refuse_held_folder("--run-dir", run_dir, [SETTINGS_FILE], "a run", remedy)


def check_new_run(settings: LearnCommandSettings) -> None:
    """The command's check: its settings, and a --run-dir free for a new run unless it resumes one there."""
    check(settings)
    check_run_dir(settings.run_dir, settings.resume)


def run(settings: LearnCommandSettings) -> int:
    Training(settings).run()
    return 0
