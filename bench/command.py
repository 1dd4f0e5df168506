"""`swimm bench sim | encoder | train [--json] [--repeat N]`: ratios measured side by side in one run;
`swimm bench learn`: algorithms x seeds learning from scratch (bench.learn).

Benchmarks are not pass/fail: they print what they measured (one JSON
object with ``--json``) so targets can be compared across machines.
On a virtual machine one run's ratio varies by about a tenth either way
(docs/benchmarks.md), so ``--repeat N`` runs it N times and reports the
median of each number, with every run's result under ``runs``.
"""

from __future__ import annotations

import importlib
import json
import logging
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from bench.host import with_host_figure
from bench.learn_settings import Layout, LearnBenchSettings
from encoder_service import Engine
from services.results import PROVENANCE_KEY, provenance
from services.settings import NonNegInt, PosInt, check_ranges

log = logging.getLogger(__name__)

BENCHMARKS = {"sim": "bench.sim", "encoder": "bench.encoder", "train": "bench.train", "learn": "bench.learn"}


@dataclass
class BenchSettings:
    target: str = field(default="sim", metadata={"positional": True})  # sim | encoder | train | learn
    json: bool = False  # print one JSON object instead of a table
    steps: NonNegInt = 0  # work per measurement; 0 = the benchmark's default
    algo: str = "sac"  # train: the learner
    envs: NonNegInt = 0  # encoder: batched half's (16); train: distributed (1); sim: grouped; learn: per run
    group_size: int = -1  # train: envs stepped as one message each way; -1 = one group per sim (from 4 envs)
    engine: Engine = "torch"  # train: the encoders' CMVAE inference, torch | onnx (onnxruntime), in both halves
    policy: str = "auto"  # train: auto (sac: sac_cmvae.zip, steady state; else scratch) | scratch | a model zip
    sims: NonNegInt = 0  # train: sims sharing the envs; 0 = two from 4 envs (an even number), else one; learn: 1
    encoders: PosInt = 1  # train: encoder processes, the learner's groups spread evenly over them
    mode: Literal["peer", "client"] = "peer"  # train: the distributed half joins as peers (as `swimm up`) or clients
    low_latency: bool = False  # train: the distributed half's processes use Zenoh's low-latency setting
    zenoh_threads: NonNegInt = 1  # train: Zenoh threads of sims, encoders, learner; 0: Zenoh's pool per runtime
    profile: str = ""  # train: write a cProfile of the distributed half's learner (CPU time) to this file
    ceiling: bool = False  # train: also run the in-process half twice at once (what two cores give it)
    repeat: PosInt = 1  # run it this many times and report each number's median (every run under "runs")
    learn: LearnBenchSettings = field(default_factory=LearnBenchSettings, metadata={"flatten": True})  # learn only


def check(settings: BenchSettings) -> None:
    """Refuse a benchmark's settings before it measures anything (exit 2, "refused its settings")."""
    check_ranges(settings)
    if settings.target not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {settings.target!r}; choose one of {', '.join(BENCHMARKS)}")
    if settings.target == "train":
        from learner_service.registry import resolve_algorithm  # torch and SB3: only for the benchmark that trains

        resolve_algorithm(settings.algo)  # an unknown name, a bad import path
    if settings.ceiling and settings.target != "train":
        raise ValueError("--ceiling is for `swimm bench train`")
    if settings.profile:
        folder = Path(settings.profile).parent
        if settings.target != "train" or settings.repeat != 1:
            raise ValueError("--profile is for one run of `swimm bench train` (without --repeat)")
        if not folder.is_dir():
            raise ValueError(f"--profile {settings.profile}: no folder {folder} to write it in")
    if settings.target == "learn":
        if settings.repeat != 1:
            raise ValueError("bench learn repeats over seeds (--seeds), not --repeat")
        importlib.import_module(BENCHMARKS["learn"]).check(settings.learn, learn_layout(settings))


def learn_layout(settings: BenchSettings) -> Layout:
    """bench learn's layout from the benchmark's ``--envs`` and ``--sims``."""
    return Layout(envs=settings.envs or 1, sims=settings.sims or 1)


def run(settings: BenchSettings) -> int:
    if settings.target == "learn":
        learn = importlib.import_module(BENCHMARKS["learn"])
        return report(learn.run(settings.learn, learn_layout(settings)), settings.json)
    module = importlib.import_module(BENCHMARKS[settings.target])
    kwargs = {"steps": settings.steps} if settings.steps else {}
    if settings.target == "train":
        kwargs["algo"] = settings.algo
        kwargs["mode"] = settings.mode
        kwargs["low_latency"] = settings.low_latency
        kwargs["zenoh_threads"] = settings.zenoh_threads
        kwargs["group_size"] = settings.group_size
        kwargs["sims"] = settings.sims
        kwargs["encoders"] = settings.encoders
        kwargs["policy"] = settings.policy
        kwargs["engine"] = settings.engine
        kwargs["profile"] = settings.profile
        kwargs["ceiling"] = settings.ceiling
    if settings.envs and settings.target in ("encoder", "train", "sim"):
        kwargs["envs"] = settings.envs
    runs = []
    for index in range(settings.repeat):
        runs.append(module.run(**kwargs))
        if settings.repeat > 1:
            log.info("run %d of %d: %s", index + 1, settings.repeat, headline(runs[-1]))
    result = runs[0] if settings.repeat == 1 else medians(runs) | {"repeat": settings.repeat, "runs": runs}
    return report(result, settings.json)


def report(result: dict, as_json: bool) -> int:
    """One JSON object, or a two-column table of the top-level keys (nested tables: ``--json``)."""
    if as_json:  # a benchmark's JSON is what gets committed: it says what made it and on how fast a host
        sys.stdout.write(json.dumps(with_provenance(result)) + "\n")
        return 0
    table = {key: value for key, value in result.items() if key not in ("runs", "settings", "how", PROVENANCE_KEY)}
    width = max(len(k) for k in table)
    for key, value in table.items():
        sys.stdout.write(f"{key:<{width}}  {value}\n")
    return 0


def with_provenance(result: dict) -> dict:
    """``result`` with its own provenance (bench learn's: the one its summary file has), one made now where it has
    none, and the host's World steps/s measured only where that lacks it: one result, one provenance."""
    about = with_host_figure(dict(result.get(PROVENANCE_KEY) or provenance()))
    rest = {key: value for key, value in result.items() if key != PROVENANCE_KEY}
    return {PROVENANCE_KEY: about, **rest}


def medians(runs: list[dict]) -> dict:
    """One result from several: each number's median, each flag true only if true in every run, the rest
    (names, settings, nested tables) as the first run gave them."""
    merged = {}
    for key, first in runs[0].items():
        values = [run[key] for run in runs]
        if isinstance(first, bool):
            merged[key] = all(values)
        elif all(value == first for value in values):
            merged[key] = first
        elif isinstance(first, (int, float)):
            merged[key] = round(float(statistics.median(values)), 3)
        else:
            merged[key] = first
    return merged


def headline(result: dict) -> str:
    """The keys a person watches while the runs go by: the rates and the ratio."""
    return ", ".join(f"{key} {value}" for key, value in result.items() if key.endswith(("ratio", "_per_s")))
