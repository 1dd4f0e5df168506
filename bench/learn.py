"""`swimm bench learn`: can the pipeline teach an algorithm from scratch, how fast, and how much do seeds differ?

Every algorithm x seed trains from scratch (no demonstrations) on cmvae observations through the distributed
pipeline, one `swimm up` after another (router, sim, encoder and learner processes), within a step and a
wall-time budget, evaluating deterministic episodes on the sim's eval channel every ``eval_every`` steps. Then
each run's final model, and the best model of its training evaluations, play ``final_episodes`` deterministic
episodes in-process on seeds the training never evaluated on (``final_seed``). The results folder:

- ``runs/<algo>-<seed>/``: the run folder of `swimm up` (``evaluations.csv`` with steps and wall seconds),
  ``final-eval/`` and ``best-eval/`` (episodes.csv, summary.json);
- ``evaluations.csv``: every run's evaluations in one table (algo, seed, steps, wall minutes, return);
- ``summary.json``: per algorithm the seeds, final returns and each final episode's, IQM with its 95% bootstrap
  interval (:mod:`bench.scores`), how many seeds reach each return threshold, best evaluation, the best model's
  return, wall minutes and steps to each threshold, and the steps each seed trained (fewer than the step budget
  where the wall-time budget ended it); with the provenance of every result file
  (services.results: command, commit, encoder hash, seeds, host, and the host's World steps/s at the end of the
  run, bench.host), which the returned summary carries too, so ``--json`` prints the same one;
- ``learn.png``: mean return across seeds against env steps and against wall minutes, with 95% bootstrap bands.

A run whose ``final-eval/summary.json`` exists is not trained again, and one whose training ran to its budget
is only evaluated, so a stopped benchmark goes on where it stopped when run again with the same ``--out``
(``--no-resume`` trains everything afresh).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from tqdm import tqdm

from bench.host import with_host_figure
from bench.learn_merge import merge
from bench.learn_settings import ONE_ENV, SUMMARY, Layout, LearnBenchSettings
from bench.scores import curve_band, final_aggregates, first_reaching
from encoder_service import DEFAULT_CHECKPOINT
from eval_service.engine import EvaluationSettings, evaluate
from learner_service import up
from learner_service.command import RESULT_FILE
from learner_service.command import check as check_learner
from learner_service.learn_settings import EvalSettings, LearnCommandSettings
from learner_service.progress import BEST_MODEL, EVALUATIONS_CSV, FINAL_MODEL
from services.results import PROVENANCE_KEY, provenance, write_result
from services.settings import ZenohSettings

log = logging.getLogger(__name__)

FINAL_EVAL = "final-eval"
BEST_EVAL = "best-eval"  # the same episodes for the best model of the training evaluations
FIGURE = "learn.png"
CURVE_POINTS = 60
NAMESPACE = "swimm/bench-learn"  # its own, so no other system on this network mistakes its processes for theirs


def run_dir(settings: LearnBenchSettings, algo: str, seed: int) -> Path:
    return Path(settings.out) / "runs" / f"{algo}-{seed}"


def learn_settings(
    settings: LearnBenchSettings, algo: str, seed: int, layout: Layout = ONE_ENV
) -> LearnCommandSettings:
    """One run's learner: the algorithm's shipped hyperparameters from scratch, evaluating every N steps."""
    evaluation = EvalSettings(
        episodes=settings.eval_episodes,
        min_steps=0,
        every=settings.eval_every,
        unit="steps",
        max_steps=settings.eval_max_steps,
    )
    return LearnCommandSettings(
        zenoh=ZenohSettings(namespace=NAMESPACE),
        algo=algo,
        obs="cmvae",
        seed=seed,
        steps=settings.budget_steps,
        budget_min=settings.budget_min,
        run_dir=str(run_dir(settings, algo, seed)),
        eval=evaluation,
        checkpoint_every=0,
        save_replay_buffer=False,
        encoder_checkpoint=settings.encoder_checkpoint,
        envs=layout.envs,
        smooth=settings.smooth,
        actor_average=settings.actor_average,
        hyperparams=settings.hyperparams,
    )


def train(settings: LearnBenchSettings, algo: str, seed: int, layout: Layout = ONE_ENV) -> None:
    """One `swimm up` to the end of its budget; refuses to go on past a learner that failed."""
    learn = learn_settings(settings, algo, seed, layout)
    folder = Path(learn.run_dir)
    if folder.exists():
        shutil.rmtree(folder)  # an unfinished run restarts: a from-scratch curve cannot be stitched together
    with contextlib.redirect_stdout(sys.stderr):  # stdout carries the benchmark's JSON alone (--json)
        code = up.run(up.UpSettings(learn=learn, port=0, sims=layout.sims))
    if code != 0 or not (folder / FINAL_MODEL).is_file():
        raise RuntimeError(f"{algo} seed {seed}: swimm up exited with {code}; see {folder / 'logs'}")


def run_result(folder: Path) -> dict[str, Any]:
    """A run's result.json (`swimm learn`'s RunResult), empty when there is none or it cannot be read."""
    try:
        result = json.loads((folder / RESULT_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return result if isinstance(result, dict) else {}


def trained(folder: Path) -> bool:
    """Whether a run's training ended by its budget (not stopped by a signal), so only its evaluation is missing."""
    return (folder / FINAL_MODEL).is_file() and run_result(folder).get("stopped_early") is False


def trained_steps(folder: Path) -> int | None:
    """The env steps a run's training ran, None without a result; below the step budget when the wall-time budget
    ended it."""
    steps = run_result(folder).get("num_timesteps")
    return steps if isinstance(steps, int) else None


def final_evaluation(
    settings: LearnBenchSettings, algo: str, seed: int, model: str = FINAL_MODEL, folder: str = FINAL_EVAL
) -> dict[str, Any]:
    """A run's ``model`` (the final one, or the best one) plays the final episodes in-process; written to (and read
    back from) ``folder`` in the run's folder."""
    out = run_dir(settings, algo, seed) / folder
    evaluation = EvaluationSettings(
        algo=[algo],
        checkpoint=[str(run_dir(settings, algo, seed) / model)],
        label=[f"{algo}-{seed}"],
        episodes=settings.final_episodes,
        seed=settings.final_seed,
        steps=settings.eval_max_steps,
        obs="cmvae",
        backend="inprocess",
        encoder_checkpoint=settings.encoder_checkpoint,
        figures=False,
    )
    evaluate(evaluation, out)
    return read_final(out)


def best_evaluation(settings: LearnBenchSettings, algo: str, seed: int) -> dict[str, Any]:
    """The best model's final episodes (``best-eval/``), read back when an earlier run of the benchmark wrote them."""
    out = run_dir(settings, algo, seed) / BEST_EVAL
    if (out / "summary.json").is_file():
        return read_final(out)
    return final_evaluation(settings, algo, seed, BEST_MODEL, BEST_EVAL)


def read_final(out: Path) -> dict[str, Any]:
    """A final evaluation's mean return, each episode's return and its Table 12 metrics (A, D, A', ..., S_A)."""
    episodes = pd.read_csv(out / "episodes.csv")
    (metrics,) = json.loads((out / "summary.json").read_text())["labels"].values()
    return {"mean_return": float(episodes["return"].mean()), "returns": episodes["return"].round(3).tolist(),
            "metrics": {key: round(float(value), 4) for key, value in metrics.items()}}  # fmt: skip


def collect(settings: LearnBenchSettings) -> pd.DataFrame:
    """Every finished run's evaluations as one table: algo, seed, num_timesteps, wall_min, mean_return, ..."""
    tables = []
    for algo in settings.algos:
        for seed in settings.seeds:
            path = run_dir(settings, algo, seed) / EVALUATIONS_CSV
            if path.is_file():
                table = pd.read_csv(path)
                table.insert(0, "seed", seed)
                table.insert(0, "algo", algo)
                table["wall_min"] = table["wall_s"] / 60.0
                tables.append(table)
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()


def summarise(
    settings: LearnBenchSettings,
    evaluations: pd.DataFrame,
    finals: dict[tuple[str, int], dict],
    layout: Layout = ONE_ENV,
    bests: dict[tuple[str, int], dict] | None = None,
) -> dict:
    """The JSON summary: per algorithm, per-seed numbers in the order of ``seeds`` and their aggregates."""
    algos = {}
    for algo in settings.algos:
        seeds = [seed for seed in settings.seeds if (algo, seed) in finals]
        finals_of = [finals[(algo, seed)]["mean_return"] for seed in seeds]
        runs = [evaluations[(evaluations["algo"] == algo) & (evaluations["seed"] == seed)] for seed in seeds]
        algos[algo] = {
            "seeds": seeds,
            "final_returns": [round(value, 1) for value in finals_of],
            **final_aggregates(finals_of, settings.thresholds),
            "final_metrics": [finals[(algo, seed)]["metrics"] for seed in seeds],
            "final_episode_returns": [finals[(algo, seed)].get("returns") for seed in seeds],
            "best_eval_returns": [round(float(run["mean_return"].max()), 1) for run in runs],
            "best_model_returns": [round(bests[(algo, seed)]["mean_return"], 1) if (algo, seed) in (bests or {})
                                   else None for seed in seeds],
            "steps": [int(run["num_timesteps"].max()) for run in runs],
            "trained_steps": [trained_steps(run_dir(settings, algo, seed)) for seed in seeds],
            "wall_min": [round(float(run["wall_min"].max()), 1) for run in runs],
            "minutes_to": {f"{t:g}": _rounded([first_reaching(run, t, "wall_min") for run in runs])
                           for t in settings.thresholds},
            "steps_to": {f"{t:g}": [first_reaching(run, t, "num_timesteps") for run in runs]
                         for t in settings.thresholds},
        }  # fmt: skip
    return {
        "algos": algos,
        "settings": dataclasses.asdict(settings) | dataclasses.asdict(layout),
        "how": "final_returns: each seed's final model, mean of final_episodes deterministic episodes (seed "
        "final_seed); IQM and its 95% percentile bootstrap over seeds; minutes_to / steps_to: the first "
        "training evaluation (eval_episodes episodes, seed 113) at or above the return, null if never; "
        "best_model_returns: the best model of those evaluations on the final episodes; seeds_reaching: how "
        "many seeds' final returns are at or above each threshold; final_episode_returns: each seed's episodes; "
        "steps: the last training evaluation's; trained_steps: the steps training ran, below budget_steps where "
        "the wall-time budget ended it",
    }


def _rounded(values: list[float | None]) -> list[float | None]:
    return [None if value is None else round(value, 1) for value in values]


def learning_figure(evaluations: pd.DataFrame) -> Figure:
    """Two panels, return against env steps and against wall minutes: each algorithm's mean across seeds and its
    95% bootstrap band."""
    figure = Figure(figsize=(12, 4.5))
    axes = figure.subplots(1, 2, sharey=True)
    for x, axis, label in (("num_timesteps", axes[0], "env steps"), ("wall_min", axes[1], "wall minutes")):
        for algo, table in evaluations.groupby("algo", sort=False):
            runs = [run for _, run in table.groupby("seed")]
            grid = np.linspace(table[x].min(), table[x].max(), CURVE_POINTS)
            band = curve_band(runs, x, grid)
            line = axis.plot(band[x], band["mean"], label=f"{algo} ({len(runs)} seed{'s' * (len(runs) > 1)})")[0]
            axis.fill_between(band[x], band["low"], band["high"], color=line.get_color(), alpha=0.2)
        axis.set_xlabel(label)
        axis.grid(alpha=0.3)
    axes[0].set_ylabel("evaluation return (mean of seeds, 95% bootstrap band)")
    axes[0].legend(loc="lower right")
    figure.suptitle("Learning from scratch on cmvae observations, distributed pipeline")
    figure.tight_layout()
    return figure


def check(settings: LearnBenchSettings, layout: Layout = ONE_ENV) -> None:
    """Refuse the benchmark's settings and every learner's (an algorithm, hyperparams, smoothing) before the first
    run starts."""
    settings.check()
    if settings.merge:
        return
    layout.check()
    for algo in settings.algos:
        check_learner(learn_settings(settings, algo, settings.seeds[0], layout))


def run(settings: LearnBenchSettings, layout: Layout = ONE_ENV) -> dict[str, Any]:
    """Train what is missing, evaluate it, write the results folder; returns the summary with its provenance."""
    check(settings, layout)
    if settings.merge:
        return write_results(Path(settings.out), *merge(settings))
    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    finals: dict[tuple[str, int], dict] = {}
    bests: dict[tuple[str, int], dict] = {}
    pairs = [(algo, seed) for algo in settings.algos for seed in settings.seeds]
    for algo, seed in tqdm(pairs, desc="bench learn", unit="run", disable=None):
        final = run_dir(settings, algo, seed) / FINAL_EVAL
        if settings.resume and (final / "summary.json").is_file():
            log.info("%s seed %d: finished earlier, kept", algo, seed)
            finals[(algo, seed)] = read_final(final)
            bests[(algo, seed)] = best_evaluation(settings, algo, seed)
            continue
        if settings.resume and trained(run_dir(settings, algo, seed)):
            log.info("%s seed %d: trained earlier, evaluating its models", algo, seed)
        else:
            log.info("%s seed %d: training from scratch (%d steps or %g min at most)", algo, seed,
                     settings.budget_steps, settings.budget_min)  # fmt: skip
            train(settings, algo, seed, layout)
            steps = trained_steps(run_dir(settings, algo, seed))
            if steps is not None and steps < settings.budget_steps:
                log.warning("%s seed %d: the %g-min wall-time budget ended training at %d of its %d steps",
                            algo, seed, settings.budget_min, steps, settings.budget_steps)  # fmt: skip
        finals[(algo, seed)] = final_evaluation(settings, algo, seed)
        bests[(algo, seed)] = best_evaluation(settings, algo, seed)
        log.info("%s seed %d: final return %.1f, best model %.1f", algo, seed, finals[(algo, seed)]["mean_return"],
                 bests[(algo, seed)]["mean_return"])  # fmt: skip
    evaluations = collect(settings)
    about = provenance({"encoder": settings.encoder_checkpoint or DEFAULT_CHECKPOINT}, seeds=settings.seeds)
    return write_results(out, summarise(settings, evaluations, finals, layout, bests), evaluations, about)


def write_results(
    out: Path, summary: dict[str, Any], evaluations: pd.DataFrame, about: dict[str, Any]
) -> dict[str, Any]:
    """The results folder: the summary (with its provenance ``about`` and, unless that has it, the host's World
    steps/s measured now, after the work), every evaluation in one table and the learning curves; returns the
    summary as written."""
    about = with_host_figure(about)
    out.mkdir(parents=True, exist_ok=True)
    evaluations.to_csv(out / EVALUATIONS_CSV, index=False)
    write_result(out / SUMMARY, summary, about)
    if not evaluations.empty:
        learning_figure(evaluations).savefig(out / FIGURE, dpi=110)
    log.info("results in %s (%s, %s, %s)", out, SUMMARY, EVALUATIONS_CSV, FIGURE)
    return {PROVENANCE_KEY: about, **summary}
