"""Self-describing result files: what made a number travels with it.

A result read months later, or by a reviewer, must say which command, code, models, seeds and machine produced
it; hosts here differ by up to 2x in speed, and shipped models get replaced. :func:`provenance` gathers those
facts once and every writer of a committed result (evaluations, suites, benchmarks) puts them under one key.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
PROVENANCE_KEY = "provenance"


def file_sha256(path: str | Path) -> str:
    """The content hash that names a model file in results, checkpoints' identities and exported metadata."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def git_state(root: Path = REPO_ROOT) -> dict[str, Any]:
    """The checkout's commit and whether tracked files differ from it; ``unknown`` outside a git checkout."""
    try:
        commit = _git(root, "rev-parse", "HEAD")
        dirty = bool(_git(root, "status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.CalledProcessError):
        return {"commit": "unknown", "dirty": None}
    return {"commit": commit, "dirty": dirty}


def _git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True,
                          timeout=10).stdout.strip()  # fmt: skip


def host() -> dict[str, Any]:
    """The machine: CPU model, logical cores, the cores this process may use, OS and Python."""
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def file_record(path: str | Path) -> dict[str, Any]:
    """A file as a result names it: its path and sha256 (None when it is not there)."""
    return {"path": str(path), "sha256": file_sha256(path) if Path(path).is_file() else None}


def provenance(
    models: Mapping[str, str | Path | None] | None = None, seeds: Iterable[int] = (), **extra: Any
) -> dict[str, Any]:
    """Command line, code, model hashes, seeds and host of a result; ``extra`` adds run-specific facts
    (a benchmark's in-process World steps/s, for one)."""
    hashed = {label: file_record(path) for label, path in (models or {}).items() if path}
    return {
        "command": shlex.join(["swimm", *sys.argv[1:]]) if _run_as_swimm() else shlex.join(sys.argv),
        "git": git_state(),
        "models": hashed,
        "seeds": list(seeds),
        "host": host(),
        "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **extra,
    }


def _run_as_swimm() -> bool:
    """Whether this process is a swimm command: the console script, the CLI module or ``python -m swimm``."""
    if not sys.argv:
        return False
    program = Path(sys.argv[0])
    return program.name in ("swimm", "cli.py") or (program.name == "__main__.py" and program.parent.name == "swimm")


def write_result(path: str | Path, record: Mapping[str, Any], about: Mapping[str, Any]) -> Path:
    """Write ``record`` as JSON with its provenance ``about`` under :data:`PROVENANCE_KEY`; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({PROVENANCE_KEY: dict(about), **record}, indent=2, default=str) + "\n")
    return path


def write_provenance_beside(table: str | Path, about: Mapping[str, Any], append: bool = False) -> Path:
    """Write a table's provenance ``about`` beside it, as ``<table>.provenance.json``, so that a CSV says what made
    it; ``append`` adds ``about`` to the runs already recorded, for a table that grows a run at a time."""
    path = Path(table).with_name(Path(table).name + ".provenance.json")
    runs = json.loads(path.read_text())["runs"] if append and path.is_file() else []
    path.write_text(json.dumps({"table": Path(table).name, "runs": [*runs, dict(about)]}, indent=2, default=str) + "\n")
    return path


def refuse_held_folder(flag: str, folder: str | Path, markers: Iterable[str], what: str, remedy: str) -> None:
    """Refuse ``folder`` where it holds any of ``markers`` (an earlier run's files, which a new run would overwrite),
    naming the flag, the folder, the files found and what to do instead."""
    held = [name for name in markers if (Path(folder) / name).is_file()]
    if held:
        raise FileExistsError(f"{flag} {folder} already holds {what} ({', '.join(held)}): {remedy}")
