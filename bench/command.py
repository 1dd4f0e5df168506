"""`swimm bench sim | encoder | train [--json]`: ratios measured side by side in one run.

Benchmarks are not pass/fail: they print what they measured (one JSON
object with ``--json``) so targets can be compared across machines.
"""

from __future__ import annotations

import importlib
import json
import logging
import sys
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

BENCHMARKS = {"sim": "bench.sim", "encoder": "bench.encoder", "train": "bench.train"}


@dataclass
class BenchSettings:
    target: str = field(default="sim", metadata={"positional": True})  # sim | encoder | train
    json: bool = False  # print one JSON object instead of a table
    steps: int = 0  # work per measurement; 0 = the benchmark's default
    algo: str = "sac"  # train: the learner
    envs: int = 16  # encoder: environments in the batched measurement
    mode: str = "peer"  # train: the distributed half's processes join Zenoh as peers (as `swimm up`) or clients
    low_latency: bool = False  # train: the distributed half's processes use Zenoh's low-latency setting


def run(settings: BenchSettings) -> int:
    if settings.target not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {settings.target!r}; choose one of {', '.join(BENCHMARKS)}")
    if settings.mode not in ("peer", "client"):
        raise ValueError(f"--mode must be peer or client, got {settings.mode!r}")
    module = importlib.import_module(BENCHMARKS[settings.target])
    kwargs = {"steps": settings.steps} if settings.steps else {}
    if settings.target == "train":
        kwargs["algo"] = settings.algo
        kwargs["mode"] = settings.mode
        kwargs["low_latency"] = settings.low_latency
    if settings.target == "encoder":
        kwargs["envs"] = settings.envs
    result = module.run(**kwargs)
    if settings.json:
        sys.stdout.write(json.dumps(result) + "\n")
    else:
        width = max(len(k) for k in result)
        for key, value in result.items():
            sys.stdout.write(f"{key:<{width}}  {value}\n")
    return 0
