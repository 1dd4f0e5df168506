"""`swimm bench learn --merge A B ...`: one results folder from the summaries of several `swimm bench learn` runs.

Each algorithm learns best with its own recipe (its own hyperparameters, smoothing and averaging), and a
benchmark of three algorithms x three seeds takes longer than one working session, so the runs behind one report
are made by several invocations. Merging takes each algorithm of ``--algos`` from the one summary that has it,
keeps that summary's settings beside it (``settings``, ``source``) and writes ``summary.json``,
``evaluations.csv`` and ``learn.png`` to ``--out`` as a training run would.

A summary is a results folder's ``summary.json`` (its ``evaluations.csv`` beside it) or a committed copy
``<name>.json`` with ``<name>-evaluations.csv`` beside it (as in docs/bench/).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from bench.learn_settings import SUMMARY, LearnBenchSettings
from learner_service.progress import EVALUATIONS_CSV


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


def merge(settings: LearnBenchSettings) -> tuple[dict[str, Any], pd.DataFrame]:
    """The merged summary and evaluations: each of ``settings.algos`` from the one source that has it."""
    sources = [(Path(path), *read_source(Path(path))) for path in settings.merge]
    algos: dict[str, Any] = {}
    tables = []
    for algo in settings.algos:
        having = [(path, summary, table) for path, summary, table in sources if algo in summary["algos"]]
        if len(having) != 1:
            found = ", ".join(str(path) for path, _, _ in having) or "none of them"
            raise ValueError(f"--merge: {algo} must be in exactly one summary, found in {found}; "
                             "pick the algorithms with --algos")  # fmt: skip
        ((path, summary, table),) = having
        algos[algo] = summary["algos"][algo] | {"settings": summary.get("settings"), "source": str(path)}
        tables.append(table[table["algo"] == algo])
    merged = {"algos": algos, "how": sources[0][1].get("how", ""), "merged_from": [str(p) for p, _, _ in sources]}
    return merged, pd.concat(tables, ignore_index=True)
