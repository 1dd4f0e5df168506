"""`swimm eval`: deterministic evaluation episodes of checkpoints (or the scripted baseline) on a live sim.

    swimm eval --algo sac --checkpoint runs/sac/best_model.zip --algo scripted --episodes 5 --seed 113 \\
        --obs state --connect tcp/127.0.0.1:7447 --namespace swimm/default --out runs/eval-sac

It discovers a live sim, claims a free env of its ``eval`` channel (a clear error if none is live or free) and
plays every contender on it in turn, from the same seed, so all of them meet the same episodes. Episodes run
``--steps`` steps without early termination. ``--backend inprocess`` plays on a World in this process instead
(offline evaluation, no sim). ``--noise`` leaves a live sim's image noise as the sim was started (``keep``, the
default) unless it names a choice: ``off``, ``on`` (the sim's configured noise, else the murky preset) or a preset
(murky, harsh); in-process, ``keep`` is clean frames. ``--latency-*`` likewise sets the camera and control delays
(sim_service.latency), left as the sim has them when not given. ``--sweep`` plays every contender across noise
severities, or with ``--sweep-kind latency`` across delays and control rates, instead (eval_service.sweep);
``--suite`` plays them in the held-out splits and has the CMVAE read each split's frames (eval_service.suite).
``--watch RUN_DIR`` re-evaluates each new best model a training run saves (eval_service.watch); ``--live-port P``
serves the live view (eval_service.live) while episodes run, and ``--live-env train/0`` adds envs that others
drive to it (eval_service.live_tap).

Contenders: each ``--algo`` in order; every algorithm but ``scripted`` takes the next ``--checkpoint``.
One ``--algo`` (default ``sac``) with several checkpoints applies to all of them. ``--label`` names them.
With no checkpoint and cmvae observations, ``sac`` means the policy to fly (:data:`SHIPPED_POLICY`, trained on
cmvae), so a bare ``swimm eval`` evaluates it; in other observation modes the default contender is ``scripted``.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from tqdm import tqdm

from eval_service.live import LiveFeed, LiveView, tap_frames
from eval_service.live_tap import EnvTap, parse_env
from eval_service.publish import ResultPublisher
from eval_service.report import PAPER_LABEL, PAPER_SAC, RunFolder
from learner_service.envs import BACKENDS, IMAGE_MODES
from learner_service.evaluation import Contender, play_episodes
from learner_service.export import SHIPPED_POLICY
from learner_service.identity import encoder_for
from learner_service.learn_settings import Backend, ObsMode, RewardVersion, TrackerGains
from learner_service.metrics import summarise
from learner_service.registry import LATENT_SCRIPTED, SCRIPTED, SCRIPTED_NAMES, Policy, load_policy, resolve_algorithm
from learner_service.task import TaskSettings
from services.results import file_sha256, provenance
from services.settings import ZenohSettings, to_dict
from sim_service.latency import LatencySettings
from sim_service.noise import EFFECTS, PRESETS

log = logging.getLogger(__name__)

KEEP_NOISE = "keep"
NOISE_CHOICES = (KEEP_NOISE, "off", "on", *(name for name in PRESETS if name != "off"))
TABLE_COLUMNS = ("mean_return", "A", "D", "A'", "D'", "C'", "S_D", "S_A")  # the paper's Table 12, return first


@dataclass
class EvalCommandSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    checkpoint: list[str] = field(default_factory=list)  # saved models (.zip), one per non-scripted --algo
    algo: list[str] = field(default_factory=list)  # sac | ppo | td3 | scripted | package.module:Class
    label: list[str] = field(default_factory=list)  # names in tables and figures (default from algo/checkpoint)
    episodes: int = 5  # deterministic evaluation episodes per contender
    seed: int = 113  # base seed: every contender plays the episodes episode_seed(seed, 1..N)
    steps: int = 3000  # steps per episode (no early termination)
    obs: ObsMode = "cmvae"  # what the policies were trained on
    reward: RewardVersion = "swimm2"
    noise: str = KEEP_NOISE  # keep (a live sim's noise as it was started) | off | on | murky | harsh
    latency: LatencySettings = field(default_factory=LatencySettings)  # --latency-*: delays (default: the sim's own)
    scripted: TrackerGains = field(default_factory=TrackerGains)  # --scripted-*: the scripted trackers' control law
    backend: Backend = "zenoh"  # zenoh (attach to a live sim) | inprocess (a World in this process)
    out: str = ""  # run folder; default runs/eval-<UTC time>
    trajectory_episode: int = 1  # the episode drawn from above
    attach_timeout_s: float = 10.0  # how long to wait for a sim's eval env to answer
    step_timeout_s: float = 2.0
    max_retries: int = 10
    encoder_checkpoint: str = ""  # in-process cmvae: the CMVAE (default: the shipped one)
    device: str = "auto"  # torch device of the policies
    threads: int = 1  # torch CPU threads; 1 keeps an idle-spinning pool off the sim's core; 0 = torch's default
    watch: str = ""  # a `swimm learn` run folder: evaluate each new best_model.zip it saves, until it finishes
    watch_interval_s: float = 5.0  # how often the watched folder is checked
    live_port: int = -1  # serve the live view on this port (0: any free port; -1: no live view)
    live_host: str = "127.0.0.1"
    live_env: list[str] = field(default_factory=list)  # also show envs others drive, e.g. train/0 (needs a live view)
    figures: bool = True  # returns, metrics and trajectory PNGs in the run folder (CSV and JSON always)
    progress_bar: bool = True  # tqdm bar on stderr
    recording: str = ""  # score the episodes of a `swimm record` MCAP file offline instead (no sim, no policy)
    sweep: bool = False  # play every contender across noise severities (eval_service.sweep) instead
    sweep_preset: str = "harsh"  # the preset whose effects the sweep scales (severity 1 = the preset)
    sweep_severities: list[float] = field(default_factory=lambda: [0.0, 0.5, 1.0, 1.5, 2.0])  # x preset; 0 = clean
    sweep_effects: list[str] = field(default_factory=lambda: ["all", *EFFECTS])  # each alone, and all together
    sweep_kind: Literal["noise", "latency"] = "noise"  # noise: effects x severities; latency: delays, control rates
    sweep_delays_ms: list[float] = field(default_factory=lambda: [0.0, 40.0, 80.0, 120.0, 160.0, 200.0, 300.0])
    sweep_rates_hz: list[float] = field(default_factory=lambda: [50.0, 25.0, 10.0])  # latency sweep: control rates
    suite: bool = False  # play every contender in the held-out splits (eval_service.suite) instead
    suite_splits: list[str] = field(default_factory=lambda: ["all"])  # which splits (sim_service.splits), or all
    suite_frames: int = 200  # reset frames per condition the CMVAE reads for its d/theta/psi errors (0: none)


def check(settings: EvalCommandSettings) -> None:
    """Refuse settings that could only fail later, saying what to change."""
    if settings.backend not in BACKENDS:
        raise ValueError(f"unknown backend {settings.backend!r}; choose one of {', '.join(BACKENDS)}")
    if settings.noise not in NOISE_CHOICES:
        raise ValueError(f"--noise must be one of {', '.join(NOISE_CHOICES)}, got {settings.noise!r}")
    if settings.recording:
        if settings.sweep or settings.watch or settings.live_port >= 0:
            raise ValueError("--recording scores a file offline: it takes no --sweep, --watch or --live-port")
        if not Path(settings.recording).is_file():
            raise FileNotFoundError(f"--recording {settings.recording}: no such file (written by `swimm record`)")
    if settings.sweep:
        from eval_service.sweep import check_sweep

        check_sweep(settings)
    if settings.suite:
        from eval_service.suite import check_suite

        check_suite(settings)
    for name in ("episodes", "steps"):
        if (value := getattr(settings, name)) < 1:
            raise ValueError(f"--{name} {value}: must be >= 1")
    settings.latency.check()
    settings.scripted.check()
    task_settings(settings)  # validates obs and reward
    if settings.live_env and settings.live_port < 0:
        raise ValueError("--live-env shows envs in the live view: give --live-port too (0 for any free port)")
    for name in settings.live_env:
        parse_env(name)


#: The trained policy shipped with the project (see docs/learner.md for the run that made it).


def task_settings(settings: EvalCommandSettings) -> TaskSettings:
    return TaskSettings(obs=settings.obs, reward=settings.reward, max_steps=settings.steps, early_termination=False)  # type: ignore[arg-type]


def contenders(settings: EvalCommandSettings) -> list[Contender]:
    """Pair algorithms with checkpoints (see the module docstring) and give each a unique label."""
    checkpoints = list(settings.checkpoint)
    shipped = settings.obs == "cmvae" and SHIPPED_POLICY.is_file()  # the shipped policy reads latents only
    algos = list(settings.algo) or (["sac"] if checkpoints or shipped else [SCRIPTED])
    if shipped and not checkpoints and algos.count("sac") == 1:
        checkpoints = [str(SHIPPED_POLICY)]
    if len(algos) == 1 and algos[0] not in SCRIPTED_NAMES and len(checkpoints) > 1:
        algos *= len(checkpoints)
    pairs: list[tuple[str, str | None]] = []
    for algo in algos:
        if algo in SCRIPTED_NAMES:
            pairs.append((algo, None))
            continue
        resolve_algorithm(algo)  # an unknown name fails here, before any sim is touched
        if not checkpoints:
            raise ValueError(f"--algo {algo} needs a --checkpoint (one per algorithm other than scripted, in order)")
        pairs.append((algo, checkpoints.pop(0)))
    if checkpoints:
        raise ValueError(f"checkpoints without an --algo: {checkpoints}")
    labels = list(settings.label) or default_labels(pairs)
    if len(labels) != len(pairs) or len(set(labels)) != len(labels):
        raise ValueError(f"--label needs {len(pairs)} distinct names (one per contender), got {labels}")
    return [Contender(label, algo, checkpoint) for label, (algo, checkpoint) in zip(labels, pairs, strict=True)]


def with_policy_encoder(settings: EvalCommandSettings) -> EvalCommandSettings:
    """``settings`` with the encoder the policies record (learner_service.identity) as ``--encoder-checkpoint``.

    A given encoder that is not the one a policy records is refused naming both; so are contenders trained on
    different encoders, since one run reads one encoder's latents.
    """
    if settings.obs != "cmvae" or settings.recording:
        return settings
    recorded: dict[str, Path] = {}
    for entry in contenders(settings):
        if entry.checkpoint is not None and entry.algo not in SCRIPTED_NAMES:
            encoder = encoder_for(entry.checkpoint, settings.encoder_checkpoint or None)
            if encoder is not None:
                recorded[entry.checkpoint] = encoder
    by_content = {file_sha256(path): (checkpoint, path) for checkpoint, path in recorded.items()}
    if len(by_content) > 1:
        pairs = "; ".join(f"{checkpoint} on {path}" for checkpoint, path in by_content.values())
        raise ValueError(f"the policies were trained on different encoders ({pairs}): evaluate them in separate runs")
    if recorded and not settings.encoder_checkpoint:
        encoder = next(iter(recorded.values()))
        log.info("the policies' encoder: %s (a live sim's encoder must run it too)", encoder)
        return dataclasses.replace(settings, encoder_checkpoint=str(encoder))
    return settings


def load_policies(settings: EvalCommandSettings, entries: list[Contender]) -> dict[str, Policy]:
    """Each contender's deterministic policy by label; the camera-only scripted tracker decodes with the CMVAE
    that makes the latents (``--encoder-checkpoint``, else the shipped one)."""
    if any(entry.algo == LATENT_SCRIPTED for entry in entries) and settings.obs != "cmvae":
        raise ValueError(f"--algo {LATENT_SCRIPTED} reads CMVAE latents: it needs --obs cmvae, not {settings.obs}")

    def checkpoint(entry: Contender) -> str | None:
        return (settings.encoder_checkpoint or None) if entry.algo == LATENT_SCRIPTED else entry.checkpoint

    if settings.threads > 0:
        import torch

        torch.set_num_threads(settings.threads)  # before the policies and the CMVAE run (docs/eval.md, threads)
    return {
        entry.label: load_policy(entry.algo, checkpoint(entry), device=settings.device, gains=settings.scripted)
        for entry in entries
    }


def default_labels(pairs: list[tuple[str, str | None]]) -> list[str]:
    """The algorithm's short name, with its checkpoint's folder and name where that algorithm appears twice."""
    names = [algo.rsplit(":", 1)[-1].lower() for algo, _ in pairs]
    labels = []
    for name, (_, checkpoint) in zip(names, pairs, strict=True):
        if names.count(name) > 1 and checkpoint is not None:
            path = Path(checkpoint)
            name = f"{name}:{path.parent.name}/{path.stem}"
        labels.append(name)
    return labels


@contextmanager
def evaluation_env(settings: EvalCommandSettings, render: bool = False) -> Iterator[Any]:
    """A claimed eval env of a live sim, or an in-process TrackingEnv (rendering when ``render`` asks for frames)."""
    task = task_settings(settings)
    if settings.backend == "zenoh":
        from eval_service.attach import attached_eval_env

        with attached_eval_env(task, settings.zenoh, settings.seed, settings.attach_timeout_s,
                               settings.step_timeout_s, settings.max_retries) as env:  # fmt: skip
            yield env
        return
    from learner_service.envs import shared_encoder
    from learner_service.inprocess_env import TrackingEnv
    from sim_service.settings import WorldSettings

    world = WorldSettings(render=render or task.obs in IMAGE_MODES)
    encoder = shared_encoder(task, checkpoint=settings.encoder_checkpoint or None)
    env = TrackingEnv(task, world, base_seed=settings.seed, encoder=encoder)
    try:
        yield env
    finally:
        env.close()


def evaluate(
    settings: EvalCommandSettings,
    out: Path,
    entries: list[Contender] | None = None,
    feed: LiveFeed | None = None,
    publisher: ResultPublisher | None = None,
    about: dict[str, Any] | None = None,
) -> dict[str, dict[str, float]]:
    """Play every contender's episodes on one env, write the run folder ``out``; returns Table 12 per label."""
    check(settings)
    settings = with_policy_encoder(settings)
    entries = entries if entries is not None else contenders(settings)
    policies = load_policies(settings, entries)
    summaries: dict[str, dict[str, float]] = {}
    options = reset_options(settings)
    started = time.perf_counter()
    with evaluation_env(settings, render=feed is not None) as env:
        folder = RunFolder(out)  # only once an env is ours: a refused evaluation leaves no half-empty run folder
        env_name = getattr(env, "name", "inprocess")
        frame = tap_frames(env) if feed is not None else None
        for entry in entries:
            bar = tqdm(total=settings.episodes * settings.steps, desc=entry.label, unit="step", unit_scale=True,
                       disable=not settings.progress_bar, file=sys.stderr, mininterval=1.0)  # fmt: skip
            source = f"{entry.label} @ {env_name}"

            def on_step(row: dict[str, Any], source: str = source, bar: tqdm = bar) -> None:
                folder.write_step(row)
                bar.update(1)
                if feed is not None and frame is not None:
                    feed.update(source, row, frame())

            def on_episode(row: dict[str, Any], entry: Contender = entry, bar: tqdm = bar) -> None:
                folder.add_episode(row)
                bar.set_postfix(ep=row["episode"], ret=f"{row['return']:.0f}")
                if publisher is not None:
                    publisher.publish("episode", row | {"checkpoint": entry.checkpoint or ""})

            with bar:
                rows = play_episodes(policies[entry.label], env, entry.label, settings.episodes, settings.seed, options,
                                     on_step, on_episode)  # fmt: skip
            summaries[entry.label] = summarise(rows)
            log.info("%s: %s", entry.label, _table_line(summaries[entry.label]))
            if publisher is not None:
                publisher.publish("summary", {"label": entry.label, "checkpoint": entry.checkpoint or "",
                                              **summaries[entry.label], **(about or {})})  # fmt: skip
    wall_s = time.perf_counter() - started
    record = {"contenders": [vars(entry) for entry in entries], "env": env_name, "wall_s": wall_s,
              "settings": to_dict(settings), "argv": sys.argv, **(about or {})}  # fmt: skip
    folder.finish(summaries, record, run_provenance(settings, entries),
                  settings.trajectory_episode if settings.figures else None)  # fmt: skip
    return summaries


def run_provenance(settings: EvalCommandSettings, entries: list[Contender]) -> dict[str, Any]:
    """What made an evaluation's numbers (services.results): contenders' and CMVAE's files, seeds, host."""
    from learner_service.task import episode_seed

    models = {entry.label: entry.checkpoint for entry in entries}
    if settings.obs == "cmvae" or (settings.suite and settings.suite_frames > 0):  # a CMVAE read the frames
        from encoder_service.inference import DEFAULT_CHECKPOINT

        models["cmvae"] = settings.encoder_checkpoint or str(DEFAULT_CHECKPOINT)
    episode_seeds = [episode_seed(settings.seed, episode) for episode in range(1, settings.episodes + 1)]
    return provenance(models, seeds=[settings.seed], episode_seeds=episode_seeds)


def noise_option(choice: str) -> bool | dict[str, Any] | None:
    """The reset option that ``--noise`` asks for: None leaves the env's noise as it is (``keep``)."""
    if choice == KEEP_NOISE:
        return None
    if choice in ("on", "off"):
        return choice == "on"
    return {"preset": choice}


def reset_options(settings: EvalCommandSettings) -> dict[str, Any]:
    """Every evaluation episode's reset options: the noise ``--noise`` names, the delays ``--latency-*`` set (each
    left out when not asked for, so a live sim keeps its own)."""
    options: dict[str, Any] = {}
    noise = noise_option(settings.noise)
    if noise is not None:
        options["noise"] = noise
    if settings.latency.enabled or settings.latency.randomise:
        options["latency"] = dataclasses.asdict(settings.latency)
    return options


def _table_line(summary: dict[str, float]) -> str:
    return ", ".join(f"{name} {summary[name]:.3g}" for name in TABLE_COLUMNS)


def default_out(prefix: str = "eval") -> Path:
    return Path("runs") / f"{prefix}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}"


def run(settings: EvalCommandSettings) -> int:
    """The CLI entry: one evaluation, or the watch loop; prints the summary table."""
    check(settings)
    out = Path(settings.out) if settings.out else default_out("eval-watch" if settings.watch else "eval")
    with ExitStack() as stack:
        feed = LiveFeed() if settings.live_port >= 0 else None
        if feed is not None:
            view = stack.enter_context(LiveView(feed, settings.live_host, settings.live_port))
            print(f"live view: {view.url}", file=sys.stderr)
            for name in settings.live_env:
                stack.enter_context(closing(EnvTap(settings.zenoh, name, feed, settings.reward)))
        # results go on the metrics key whenever there is a Zenoh network to put them on (not in-process)
        publish = settings.backend == "zenoh" and not settings.recording
        publisher = stack.enter_context(closing(ResultPublisher(settings.zenoh))) if publish else None
        if settings.sweep:
            from eval_service.sweep import sweep

            sweep(settings, out)
            return 0
        if settings.suite:
            from eval_service.suite import run_suite

            run_suite(settings, out)
            return 0
        if settings.watch:
            from eval_service.watch import watch

            watch(settings, Path(settings.watch), out, feed, publisher)
            return 0
        if settings.recording:
            summaries = score_offline(settings, out)
        else:
            summaries = evaluate(settings, out, feed=feed, publisher=publisher)
    print_table(summaries, out)
    return 0


def score_offline(settings: EvalCommandSettings, out: Path) -> dict[str, dict[str, float]]:
    """``--recording``: every recorded episode scored, one label per env, written like a live evaluation."""
    from eval_service.offline import score_recording

    rows = score_recording(settings.recording, settings.reward)
    folder = RunFolder(out)
    for row in rows:
        folder.add_episode(row)
    labels = dict.fromkeys(row["label"] for row in rows)
    summaries = {label: summarise([row for row in rows if row["label"] == label]) for label in labels}
    record = {"recording": settings.recording, "settings": to_dict(settings), "argv": sys.argv}
    folder.finish(summaries, record, provenance({"recording": settings.recording}), None)
    return summaries


def print_table(summaries: dict[str, dict[str, float]], out: Path) -> None:
    """Table 12 on stdout, one line per label and the paper's SAC last."""
    width = max(len(label) for label in [*summaries, PAPER_LABEL]) + 2
    print("".ljust(width) + "".join(name.rjust(11) for name in TABLE_COLUMNS))
    for label, summary in [*summaries.items(), (PAPER_LABEL, PAPER_SAC)]:
        print(label.ljust(width) + "".join(f"{summary[name]:11.3g}" for name in TABLE_COLUMNS))
    print(f"run folder: {out}")
