"""The evaluation engine: contenders, their policies and encoder, the env they play on, and a run's provenance.

Every `swimm eval` run (a plain evaluation, a watch, a sweep, a suite) plays contenders through these functions,
from :class:`EvaluationSettings`; the commands (eval_service.command and the modules it names) add their own
settings and outputs around them.

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
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import torch
from tqdm import tqdm

from encoder_service import DEFAULT_CHECKPOINT
from eval_service.attach import attached_eval_env
from eval_service.live import LiveFeed, tap_frames
from eval_service.paired import describe_ratio, return_ratios
from eval_service.publish import ResultPublisher
from eval_service.report import RunFolder
from learner_service.envs import BACKENDS, shared_encoder
from learner_service.evaluation import Contender, play_episodes
from learner_service.export import SHIPPED_POLICY
from learner_service.identity import encoder_for, read_identity
from learner_service.learn_settings import Backend, ObsMode, RewardVersion, TaskName, TrackerGains, check_sim_config
from learner_service.metrics import IDENTITY_COLUMNS, summarise
from learner_service.registry import LATENT_SCRIPTED, SCRIPTED, SCRIPTED_NAMES, Policy, load_policy, resolve_algorithm
from learner_service.task import TaskSettings, episode_seed
from services.results import file_record, file_sha256, provenance
from services.settings import FilePath, ZenohSettings, to_dict
from sim_service.latency import LatencySettings
from sim_service.noise import PRESETS
from sim_service.settings import PodSettings, world_of_file

log = logging.getLogger(__name__)
S = TypeVar("S", bound="EvaluationSettings")

KEEP_NOISE = "keep"
NOISE_CHOICES = (KEEP_NOISE, "off", "on", *(name for name in PRESETS if name != "off"))
TABLE_COLUMNS = ("mean_return", "A", "D", "A'", "D'", "C'", "S_D", "S_A")  # the paper's Table 12, return first
VERTICAL_COLUMNS = ("E", "S_H")  # what the 3d task's summaries add to the table


@dataclass
class EvaluationSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    checkpoint: list[FilePath] = field(default_factory=list)  # saved models (.zip), one per non-scripted --algo
    algo: list[str] = field(default_factory=list)  # sac | ppo | td3 | scripted | package.module:Class
    label: list[str] = field(default_factory=list)  # names in tables and figures (default from algo/checkpoint)
    episodes: int = 5  # deterministic evaluation episodes per contender
    seed: int = 113  # base seed: every contender plays the episodes episode_seed(seed, 1..N)
    steps: int = 3000  # steps per episode (no early termination)
    obs: ObsMode = "cmvae"  # what the policies were trained on
    reward: RewardVersion = "swimm2"
    task: TaskName = "planar"  # planar | 3d (in-process: the 3d dolphin too; a live sim needs --dolphin-motion 3d)
    noise: str = KEEP_NOISE  # keep (a live sim's noise as it was started) | off | on | murky | harsh
    latency: LatencySettings = field(default_factory=LatencySettings)  # --latency-*: delays (default: the sim's own)
    scripted: TrackerGains = field(default_factory=TrackerGains)  # --scripted-*: the scripted trackers' control law
    backend: Backend = "zenoh"  # zenoh (attach to a live sim) | inprocess (a World in this process)
    # --dolphin-pod-size, --dolphin-pod-crossing: the in-process world's pod (a live sim's is its own, same flags).
    pod: PodSettings = field(default_factory=PodSettings, metadata={"stem": "dolphin_pod"})
    sim_config: FilePath = ""  # in-process: the world of a `swimm sim` settings file (noise, scenery, render, pod)
    trajectory_episode: int = 1  # the episode drawn from above
    attach_timeout_s: float = 10.0  # how long to wait for a sim's eval env to answer
    step_timeout_s: float = 2.0
    max_retries: int = 10
    encoder_checkpoint: FilePath = ""  # in-process cmvae: the CMVAE (default: the shipped one)
    device: str = "auto"  # torch device of the policies
    threads: int = 1  # torch CPU threads; 1 keeps an idle-spinning pool off the sim's core; 0 = torch's default
    figures: bool = True  # returns, metrics and trajectory PNGs in the run folder (CSV and JSON always)
    progress_bar: bool = True  # tqdm bar on stderr


def check_evaluation(settings: EvaluationSettings) -> None:
    """Refuse evaluation settings that could only fail later, saying what to change."""
    if settings.backend not in BACKENDS:
        raise ValueError(f"unknown backend {settings.backend!r}; choose one of {', '.join(BACKENDS)}")
    if settings.noise not in NOISE_CHOICES:
        raise ValueError(f"--noise must be one of {', '.join(NOISE_CHOICES)}, got {settings.noise!r}")
    for name in ("episodes", "steps"):
        if (value := getattr(settings, name)) < 1:
            raise ValueError(f"--{name} {value}: must be >= 1")
    settings.latency.check()
    settings.scripted.check()
    settings.pod.check()
    if settings.backend == "zenoh" and settings.pod != PodSettings():
        raise ValueError("--dolphin-pod-* build the in-process world's pod: start the live sim with them instead")
    if settings.backend == "zenoh" and settings.sim_config:
        raise ValueError(f"--sim-config {settings.sim_config} builds the in-process world: a live sim serves its own; "
                         "start it with `swimm sim --config` instead")  # fmt: skip
    check_sim_config(settings.sim_config)
    named = [("--checkpoint", path) for path in settings.checkpoint]
    named.append(("--encoder-checkpoint", settings.encoder_checkpoint))
    for flag, path in named:  # before any wait for a live sim
        if path and not Path(path).is_file():
            raise FileNotFoundError(f"{flag} {path}: no such file")
    task_settings(settings)  # validates obs and reward
    if settings.obs == "cmvae":
        policies_encoder(settings)  # a policy and an encoder that are no pair, a file that is no policy
    else:
        for path in settings.checkpoint:
            read_identity(path)  # a file that is no policy checkpoint


def task_settings(settings: EvaluationSettings) -> TaskSettings:
    return TaskSettings(obs=settings.obs, reward=settings.reward, task=settings.task, max_steps=settings.steps,  # type: ignore[arg-type]
                        early_termination=False)  # fmt: skip


def cmvae_in_use(settings: EvaluationSettings) -> str:
    """The CMVAE that reads the frames: ``--encoder-checkpoint``, else the shipped one."""
    return settings.encoder_checkpoint or str(DEFAULT_CHECKPOINT)


def contenders(settings: EvaluationSettings) -> list[Contender]:
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


def with_policy_encoder(settings: S) -> S:
    """``settings`` with the encoder the policies record (learner_service.identity) as ``--encoder-checkpoint``,
    refused as :func:`policies_encoder` refuses them."""
    if settings.obs != "cmvae":
        return settings
    encoder = policies_encoder(settings)
    if encoder is not None and not settings.encoder_checkpoint:
        log.info("the policies' encoder: %s (a live sim's encoder must run it too)", encoder)
        return dataclasses.replace(settings, encoder_checkpoint=str(encoder))
    return settings


def policies_encoder(settings: EvaluationSettings) -> Path | None:
    """The one encoder the contenders' policies record, None where none records one.

    A given encoder that is not the one a policy records is refused naming both; so are contenders trained on
    different encoders, since one run reads one encoder's latents; so is a file that is no policy checkpoint.
    """
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
    return next(iter(recorded.values()), None)


def load_policies(settings: EvaluationSettings, entries: list[Contender]) -> dict[str, Policy]:
    """Each contender's deterministic policy by label; the camera-only scripted tracker decodes with the CMVAE
    that makes the latents (``--encoder-checkpoint``, else the shipped one)."""
    if any(entry.algo == LATENT_SCRIPTED for entry in entries) and settings.obs != "cmvae":
        raise ValueError(f"--algo {LATENT_SCRIPTED} reads CMVAE latents: it needs --obs cmvae, not {settings.obs}")

    def checkpoint(entry: Contender) -> str | None:
        return (settings.encoder_checkpoint or None) if entry.algo == LATENT_SCRIPTED else entry.checkpoint

    if settings.threads > 0:
        torch.set_num_threads(settings.threads)  # before the policies and the CMVAE run (docs/eval.md, threads)
    return {
        entry.label: load_policy(
            entry.algo, checkpoint(entry), device=settings.device, gains=settings.scripted, task=settings.task
        )
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
def evaluation_env(settings: EvaluationSettings, render: bool = False) -> Iterator[Any]:
    """A claimed eval env of a live sim, or an in-process TrackingEnv (rendering when ``render`` asks for frames)."""
    task = task_settings(settings)
    if settings.backend == "zenoh":
        encoder = cmvae_in_use(settings) if settings.obs == "cmvae" else None
        with attached_eval_env(task, settings.zenoh, settings.seed, settings.attach_timeout_s,
                               settings.step_timeout_s, settings.max_retries, encoder) as env:  # fmt: skip
            yield env
        return
    # MuJoCo: not in the torch image
    from learner_service.inprocess_env import TrackingEnv, task_world

    world = task_world(task, render, world_of_file(settings.sim_config) if settings.sim_config else None)
    if settings.pod != PodSettings():  # the flags' pod over the settings file's
        world.dolphin = dataclasses.replace(
            world.dolphin, pod_size=settings.pod.size, pod_crossing=settings.pod.crossing
        )
    encoder = shared_encoder(task, checkpoint=settings.encoder_checkpoint or None)
    env = TrackingEnv(task, world, base_seed=settings.seed, encoder=encoder)
    try:
        yield env
    finally:
        env.close()


def evaluate(
    settings: EvaluationSettings,
    out: Path,
    entries: list[Contender] | None = None,
    feed: LiveFeed | None = None,
    publisher: ResultPublisher | None = None,
    about: dict[str, Any] | None = None,
) -> dict[str, dict[str, float]]:
    """Play every contender's episodes on one env, write the run folder ``out``; returns Table 12 per label."""
    check_evaluation(settings)
    settings = with_policy_encoder(settings)
    entries = entries if entries is not None else contenders(settings)
    policies = load_policies(settings, entries)
    summaries: dict[str, dict[str, float]] = {}
    returns: dict[str, list[float]] = {}  # per label, episode by episode: the same episodes for every contender
    options = reset_options(settings)
    started = time.perf_counter()
    with evaluation_env(settings, render=feed is not None) as env:
        # only once an env is ours: a refused evaluation leaves no half-empty run folder
        folder = RunFolder(out, vertical=settings.task == "3d")
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
            returns[entry.label] = [row["return"] for row in rows]
            log.info("%s: %s", entry.label, table_line(summaries[entry.label]))
            if publisher is not None:
                publisher.publish("summary", {"label": entry.label, "checkpoint": entry.checkpoint or "",
                                              **summaries[entry.label], **(about or {})})  # fmt: skip
    wall_s = time.perf_counter() - started
    ratios = return_ratios(returns)
    for label, ratio in ratios.items():
        log.info("%s", describe_ratio(label, ratio))
    record = {"contenders": [vars(entry) for entry in entries], "return_ratios": ratios, "env": env_name,
              "wall_s": wall_s, "settings": to_dict(settings), "argv": sys.argv, **(about or {})}  # fmt: skip
    folder.finish(summaries, record, run_provenance(settings, entries),
                  settings.trajectory_episode if settings.figures else None)  # fmt: skip
    return summaries


def play_plan(
    settings: EvaluationSettings,
    entries: list[Contender],
    policies: dict[str, Policy],
    plan: list[tuple[dict[str, Any], dict[str, Any]]],
    desc: str,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], float]:
    """Every contender's episodes in every condition of ``plan`` ((columns naming it, reset options)), on one env.

    Returns one row per contender and condition (its columns, Table 12, the share of episodes with a violation),
    one row per episode, and the wall time. The sweep (eval_service.sweep) and the suite (eval_service.suite)
    share it.
    """
    rows: list[dict[str, Any]] = []
    episodes: list[dict[str, Any]] = []
    started = time.perf_counter()
    total = len(plan) * len(entries) * settings.episodes * settings.steps
    with evaluation_env(settings) as env, tqdm(total=total, desc=desc, unit="step", unit_scale=True,
                                               disable=not settings.progress_bar, file=sys.stderr,
                                               mininterval=1.0) as bar:  # fmt: skip
        for columns, options in plan:
            for entry in entries:
                bar.set_postfix(**columns, label=entry.label)
                played = play_episodes(policies[entry.label], env, entry.label, settings.episodes, settings.seed,
                                       options, on_step=lambda *_: bar.update(1))  # fmt: skip
                summary = summarise(played)
                violations = sum(bool(r["left_view"] or r["distance_exceeded"] or r["collided"]) for r in played)
                rows.append({"label": entry.label, **columns, **summary, "violations": violations / len(played)})
                episodes += [{"label": entry.label, **columns, **r} for r in played]
                log.info("%s, %s: return %.0f, violations in %d of %d episodes", entry.label,
                         " ".join(str(value) for value in columns.values()), summary["mean_return"], violations,
                         len(played))  # fmt: skip
    return rows, episodes, time.perf_counter() - started


def run_provenance(settings: EvaluationSettings, entries: list[Contender], cmvae_reads: bool = False) -> dict[str, Any]:
    """What made an evaluation's numbers (services.results): contenders' and CMVAE's files, seeds, host.

    ``cmvae_reads``: a CMVAE read frames besides the policies' observations (the suite's encoder check)."""
    models = {entry.label: entry.checkpoint for entry in entries}
    if settings.obs == "cmvae" or cmvae_reads:
        models["cmvae"] = cmvae_in_use(settings)
    episode_seeds = [episode_seed(settings.seed, episode) for episode in range(1, settings.episodes + 1)]
    world_file = {"sim_config": file_record(settings.sim_config)} if settings.sim_config else {}
    return provenance(models, seeds=[settings.seed], episode_seeds=episode_seeds, **world_file)


def noise_option(choice: str) -> bool | dict[str, Any] | None:
    """The reset option that ``--noise`` asks for: None leaves the env's noise as it is (``keep``)."""
    if choice == KEEP_NOISE:
        return None
    if choice in ("on", "off"):
        return choice == "on"
    return {"preset": choice}


def reset_options(settings: EvaluationSettings) -> dict[str, Any]:
    """Every evaluation episode's reset options: the noise ``--noise`` names, the delays ``--latency-*`` set (each
    left out when not asked for, so a live sim keeps its own)."""
    options: dict[str, Any] = {}
    noise = noise_option(settings.noise)
    if noise is not None:
        options["noise"] = noise
    if settings.latency.enabled or settings.latency.randomise:
        options["latency"] = dataclasses.asdict(settings.latency)
    return options


def vertical_columns(settings: EvaluationSettings) -> tuple[str, ...]:
    """What the 3d task's tables (sweep, suite) add to Table 12's columns."""
    return VERTICAL_COLUMNS if settings.task == "3d" else ()


def table_columns(summaries: Iterable[dict[str, float]]) -> tuple[str, ...]:
    """Table 12's columns, with E when the summaries are the 3d task's and the identity columns when a pod's."""
    summaries = list(summaries)
    vertical = VERTICAL_COLUMNS if all("E" in summary for summary in summaries) else ()
    identity = IDENTITY_COLUMNS if all("identity_kept" in summary for summary in summaries) else ()
    return TABLE_COLUMNS + vertical + identity


def table_line(summary: dict[str, float]) -> str:
    return ", ".join(f"{name} {summary[name]:.3g}" for name in table_columns([summary]))
