"""`swimm bench learn --merge A B ...`: one results folder from the summaries of several `swimm bench learn` runs.

Each algorithm learns best with its own recipe (its own hyperparameters, smoothing and averaging), and a
benchmark of three algorithms x five seeds takes longer than one working session, so the runs behind one report
are made by several invocations. Merging takes each algorithm of ``--algos`` from the summaries that have it (one
recipe's seeds may come from several runs: they are pooled, and the aggregates computed again over them all),
keeps the recipe's settings beside it (``settings``, ``sources``) and writes ``summary.json``,
``evaluations.csv`` and ``learn.png`` to ``--out`` as a training run would. Its provenance names the seeds pooled,
the encoder the sources' provenance names, where they all name the same one, and each source's host.

A summary is a results folder's ``summary.json`` (its ``evaluations.csv`` beside it) or a committed copy
``<name>.json`` with ``<name>-evaluations.csv`` beside it (as in docs/bench/).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pandas as pd

from bench.host import HOST_FIGURE
from bench.learn_settings import SUMMARY, LearnBenchSettings
from bench.scores import final_aggregates
from learner_service.progress import EVALUATIONS_CSV
from services.results import PROVENANCE_KEY, provenance


def evaluations_of(summary: Path) -> Path:
    """The evaluations table that goes with a summary file."""
    if summary.name == SUMMARY:
        return summary.with_name(EVALUATIONS_CSV)
    return summary.with_name(f"{summary.stem}-evaluations.csv")


def read_source(path: Path) -> tuple[dict[str, Any], pd.DataFrame]:
    """A summary and its evaluations, or ValueError naming the file that is missing or not a summary."""
    table = evaluations_of(path)
    for needed in (path, table):
        if not needed.is_file():
            raise ValueError(f"--merge {path}: no such file {needed}")
    try:
        summary = json.loads(path.read_text())
    except ValueError as exc:
        raise ValueError(f"--merge {path}: not JSON ({exc})") from exc
    if not isinstance(summary, dict) or not isinstance(summary.get("algos"), dict):
        raise ValueError(f"--merge {path}: not a `swimm bench learn` summary (no 'algos' mapping)")
    return summary, pd.read_csv(table)


def merge(settings: LearnBenchSettings) -> tuple[dict[str, Any], pd.DataFrame, dict[str, Any]]:
    """The merged summary, evaluations and provenance: each of ``settings.algos`` from the summaries that have it,
    its seeds pooled where several ran one recipe on other seeds."""
    sources = [(Path(path), *read_source(Path(path))) for path in settings.merge]
    algos: dict[str, Any] = {}
    tables = []
    for algo in settings.algos:
        having = [(path, summary, table) for path, summary, table in sources if algo in summary["algos"]]
        if not having:
            raise ValueError(f"--merge: {algo} is in none of the summaries; pick the algorithms with --algos")
        algos[algo] = pooled(algo, having, settings.thresholds)
        tables += [table[table["algo"] == algo] for _, _, table in having]
    merged = {"algos": algos, "how": sources[0][1].get("how", ""), "merged_from": [str(p) for p, _, _ in sources]}
    used = [(path, summary) for path, summary, _ in sources if summary["algos"].keys() & set(settings.algos)]
    return merged, pd.concat(tables, ignore_index=True), merged_provenance(algos, used)


def merged_provenance(algos: dict[str, Any], sources: list[tuple[Path, dict[str, Any]]]) -> dict[str, Any]:
    """The merge's provenance with the seeds behind its numbers: every algorithm's, in first-seen order; the
    models its ``sources`` ran; and the hosts they ran on. Its own host figure stays null: the merge trains
    nothing, and its wall times are the sources' hosts'."""
    seeds = dict.fromkeys(seed for entry in algos.values() for seed in entry["seeds"])
    summaries = [summary for _, summary in sources]
    return provenance(seeds=seeds) | {
        "models": agreed_models(summaries),
        HOST_FIGURE: None,
        "source_hosts": [source_host(path, summary) for path, summary in sources],
    }


def source_host(path: Path, summary: dict[str, Any]) -> dict[str, Any]:
    """Where a merged summary ran, as its provenance says (nulls for a summary from before provenance)."""
    about = summary.get(PROVENANCE_KEY) or {}
    return {"summary": str(path), "host": about.get("host"),
            HOST_FIGURE: about.get(HOST_FIGURE)}  # fmt: skip


def agreed_models(summaries: list[dict[str, Any]]) -> dict[str, Any]:
    """The models (label, path, hash) the first summary's provenance names, if every summary's names the same
    hashes; none otherwise, where a source records other models or none, as summaries from before provenance."""
    recorded = [(summary.get(PROVENANCE_KEY) or {}).get("models") or {} for summary in summaries]
    hashes = [{label: model.get("sha256") for label, model in models.items()} for models in recorded]
    return recorded[0] if all(named == hashes[0] for named in hashes) else {}


#: Settings that name a run, not its recipe: summaries of one recipe on other seeds differ in these alone.
RUN_ONLY = ("seeds", "out", "resume", "merge")
#: The wall-time cap: a host's speed, not the recipe, where it ended no run (the runs trained their step budget).
WALL_CAP = "budget_min"
#: Per-seed fields of a summary's algorithm entry, and those holding per-seed lists under each threshold.
PER_SEED = ("final_returns", "final_metrics", "final_episode_returns", "best_eval_returns", "best_model_returns",
            "steps", "trained_steps", "wall_min")  # fmt: skip
PER_SEED_BY_THRESHOLD = ("minutes_to", "steps_to")


def pooled(algo: str, having: list[tuple[Path, dict, pd.DataFrame]], thresholds: list[float]) -> dict[str, Any]:
    """``algo``'s entry from one summary, or its seeds pooled from several that ran the same recipe (aggregates
    computed again over every seed); a different recipe or a seed run twice is refused by name."""
    (first_path, first, _), *others = having
    recipe, first_uncapped = _recipe(first), _cap_ended_no_run(first, algo)
    for path, summary, _ in others:
        other = _recipe(summary)
        differ = sorted(key for key in recipe.keys() | other.keys() if recipe.get(key) != other.get(key))
        if first_uncapped and _cap_ended_no_run(summary, algo):
            differ = [key for key in differ if key != WALL_CAP]
        if differ:
            raise ValueError(f"--merge: {algo} is in {first_path} and {path}, which ran different recipes "
                             f"({', '.join(differ)} differ); merge the seeds of one recipe only")  # fmt: skip
    entries = [summary["algos"][algo] for _, summary, _ in having]
    seeds = [seed for entry in entries for seed in entry["seeds"]]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--merge: {algo} has a seed in two summaries (seeds {seeds}); each seed counts once")
    entry = dict(entries[0])  # a field older summaries lack reads None for their seeds; aggregates are made anew
    for field in PER_SEED:
        entry[field] = [value for e in entries for value in e.get(field) or [None] * len(e["seeds"])]
    for field in PER_SEED_BY_THRESHOLD:
        keys = dict.fromkeys(key for e in entries for key in e.get(field, {}))
        entry[field] = {key: [value for e in entries for value in e.get(field, {}).get(key) or [None] * len(e["seeds"])]
                        for key in keys}  # fmt: skip
    entry |= {"seeds": seeds, **final_aggregates(entry["final_returns"], thresholds)}
    settings = first.get("settings") or {}
    return entry | {"settings": settings | {"seeds": seeds} if settings else settings,
                    "sources": [str(path) for path, _, _ in having]}  # fmt: skip


def _cap_ended_no_run(summary: dict[str, Any], algo: str) -> bool:
    """Whether every seed of ``algo`` in ``summary`` trained its whole step budget inside the wall-time cap (read from
    ``trained_steps``, or in older summaries from each run's minutes): then the cap shaped none of its results."""
    settings, entry = summary.get("settings") or {}, summary["algos"][algo]
    if entry.get("trained_steps"):
        return all(steps is not None and steps >= settings.get("budget_steps", 0) for steps in entry["trained_steps"])
    cap, minutes = settings.get("budget_min"), entry.get("wall_min")
    return bool(cap and minutes) and all(value is not None and value < cap for value in minutes)


def _recipe(summary: dict[str, Any]) -> dict[str, Any]:
    """A summary's settings less those that name the run, a setting added since it ran read at its default."""
    settings = _with_defaults(summary.get("settings") or {}, dataclasses.asdict(LearnBenchSettings()))
    return {key: value for key, value in settings.items() if key not in RUN_ONLY}


def _with_defaults(values: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    filled = defaults | values
    return {key: _with_defaults(value, defaults[key]) if isinstance(value, dict) and isinstance(defaults.get(key), dict)
            else value for key, value in filled.items()}  # fmt: skip
