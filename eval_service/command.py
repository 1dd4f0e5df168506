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
drive to it (eval_service.live_tap). ``--recording`` scores a `swimm record` file offline (eval_service.offline).

Which contenders play, on which env and encoder, is the evaluation engine's (eval_service.engine); this module
picks the run among these and holds each one's settings group.
"""

from __future__ import annotations

import sys
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from eval_service.engine import EvaluationSettings, check_evaluation, evaluate, table_columns
from eval_service.live import LiveFeed, LiveSettings, LiveView
from eval_service.live_tap import EnvTap, parse_env
from eval_service.offline import score_recording
from eval_service.publish import ResultPublisher
from eval_service.report import PAPER_LABEL, PAPER_SAC, RunFolder
from eval_service.suite import SuiteSettings, check_suite, run_suite
from eval_service.sweep import SweepSettings, check_sweep, sweep
from eval_service.watch import WATCH_TABLE, watch
from learner_service.metrics import summarise
from services.record import recorded_namespace
from services.results import provenance, refuse_held_folder
from services.settings import to_dict


@dataclass
class EvalCommandSettings(EvaluationSettings):
    """The engine's settings (eval_service.engine), then which run: a plain evaluation, a watch, a sweep, a suite
    or a recording scored offline, each with its own group of flags."""

    out: str = ""  # run folder; default runs/eval-<UTC time>
    overwrite: bool = False  # replace the evaluation an --out folder already holds instead of refusing it
    live: LiveSettings = field(default_factory=LiveSettings)  # --live-*: the live view while episodes run
    watch: str = ""  # a `swimm learn` run folder: evaluate each new best_model.zip it saves, until it finishes
    watch_interval_s: float = 5.0  # how often the watched folder is checked
    recording: str = ""  # score the episodes of a `swimm record` MCAP file offline instead (no sim, no policy)
    sweep: bool = False  # play every contender across noise severities (eval_service.sweep) instead
    sweep_plan: SweepSettings = field(default_factory=SweepSettings, metadata={"stem": "sweep"})  # --sweep-*
    suite: bool = False  # play every contender in the held-out splits (eval_service.suite) instead
    suite_plan: SuiteSettings = field(default_factory=SuiteSettings, metadata={"stem": "suite"})  # --suite-*


# What any of the runs below leaves in its folder: a folder holding one holds an earlier evaluation.
RESULT_FILES = ("summary.json", "steps.csv", "episodes.csv", "sweep.json", "suite.json", WATCH_TABLE)


def check_out(out: str, overwrite: bool) -> None:
    """Refuse an --out folder whose earlier evaluation this one would overwrite, unless told to."""
    if out and not overwrite:
        refuse_held_folder("--out", out, RESULT_FILES, "an evaluation",
                           "choose another --out, or give --overwrite to replace it")  # fmt: skip


def check(settings: EvalCommandSettings) -> None:
    """Refuse settings that could only fail later, saying what to change."""
    check_evaluation(settings)
    check_out(settings.out, settings.overwrite)
    if settings.recording:
        if settings.sweep or settings.watch or settings.live.port >= 0:
            raise ValueError("--recording scores a file offline: it takes no --sweep, --watch or --live-port")
        if not Path(settings.recording).is_file():
            raise FileNotFoundError(f"--recording {settings.recording}: no such file (written by `swimm record`)")
        recorded_namespace(settings.recording)  # a file that is no swimm recording
    if settings.sweep:
        check_sweep(settings.sweep_plan)
        if settings.watch:
            raise ValueError("--sweep and --watch are two different runs: give one")
    if settings.suite:
        check_suite(settings.suite_plan)
        if settings.sweep or settings.watch or settings.recording:
            raise ValueError("--suite is a run of its own: it takes no --sweep, --watch or --recording")
    if settings.watch and not Path(settings.watch).is_dir():
        raise FileNotFoundError(f"--watch {settings.watch}: nothing to watch, no run folder of `swimm learn` there")
    if settings.live.env and settings.live.port < 0:
        raise ValueError("--live-env shows envs in the live view: give --live-port too (0 for any free port)")
    for name in settings.live.env:
        parse_env(name)


def default_out(prefix: str = "eval") -> Path:
    return Path("runs") / f"{prefix}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}"


def run(settings: EvalCommandSettings) -> int:
    """The CLI entry: one evaluation, or the watch loop; prints the summary table."""
    check(settings)
    out = Path(settings.out) if settings.out else default_out("eval-watch" if settings.watch else "eval")
    with ExitStack() as stack:
        feed = LiveFeed() if settings.live.port >= 0 else None
        if feed is not None:
            view = stack.enter_context(LiveView(feed, settings.live.host, settings.live.port))
            print(f"live view: {view.url}", file=sys.stderr)
            for name in settings.live.env:
                stack.enter_context(EnvTap(settings.zenoh, name, feed, settings.reward, settings.task))
        # results go on the metrics key whenever there is a Zenoh network to put them on (not in-process)
        publish = settings.backend == "zenoh" and not settings.recording
        publisher = stack.enter_context(ResultPublisher(settings.zenoh)) if publish else None
        if settings.sweep:
            sweep(settings, settings.sweep_plan, out)
            return 0
        if settings.suite:
            run_suite(settings, settings.suite_plan, out)
            return 0
        if settings.watch:
            watch(settings, Path(settings.watch), out, feed, publisher, settings.watch_interval_s)
            return 0
        if settings.recording:
            summaries = score_offline(settings, out)
        else:
            summaries = evaluate(settings, out, feed=feed, publisher=publisher)
    print_table(summaries, out)
    return 0


def score_offline(settings: EvalCommandSettings, out: Path) -> dict[str, dict[str, float]]:
    """``--recording``: every recorded episode scored, one label per env, written like a live evaluation."""
    rows = score_recording(settings.recording, settings.reward, settings.task)
    folder = RunFolder(out, vertical=settings.task == "3d")
    for row in rows:
        folder.add_episode(row)
    labels = dict.fromkeys(row["label"] for row in rows)
    summaries = {label: summarise([row for row in rows if row["label"] == label]) for label in labels}
    record = {"recording": settings.recording, "settings": to_dict(settings), "argv": sys.argv}
    folder.finish(summaries, record, provenance({"recording": settings.recording}), None)
    return summaries


def print_table(summaries: dict[str, dict[str, float]], out: Path) -> None:
    """Table 12 on stdout (with E for the 3d task, the identity columns for a pod), one line per label and the paper's
    SAC last (it has neither)."""
    width = max(len(label) for label in [*summaries, PAPER_LABEL]) + 2
    columns = table_columns(summaries.values())
    widths = [max(11, len(name) + 2) for name in columns]  # a pod's identity columns have longer names
    print("".ljust(width) + "".join(name.rjust(w) for name, w in zip(columns, widths, strict=True)))
    for label, summary in [*summaries.items(), (PAPER_LABEL, PAPER_SAC)]:
        print(label.ljust(width) + "".join(f"{summary[name]:{w}.3g}" if name in summary else "-".rjust(w)
                                           for name, w in zip(columns, widths, strict=True)))  # fmt: skip
    print(f"run folder: {out}")
