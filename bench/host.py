"""The host's yardstick, one in-process World's steps/s (64x64 frames), measured in a process of its own.

Every committed speed figure carries it, since hosts here differ by up to 2x. Mesa fixes its rasteriser threads
(``LP_NUM_THREADS``) at a process's first frame, and at 64x64 its default of one thread per core renders about half
as fast as drawing on the stepping thread, which every swimm process does: measured in the caller's process the
yardstick would depend on how the caller happened to start. ``python -m bench.host [STEPS]`` prints it, and
:func:`host_world_steps_per_s` runs it for every benchmark's ``--json`` provenance (bench/command.py) and for the
provenance of `swimm bench learn`'s summary (bench/learn.py).
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
from contextlib import ExitStack

from bench.sim import Tally, random_actions, step_inprocess, warm_world
from services.process import DEFAULT_RENDER_THREADS, ProcessSettings, child_environment, configure_process

log = logging.getLogger(__name__)

#: The provenance key of the yardstick's figure.
HOST_FIGURE = "host_world_steps_per_s"
#: How long measuring the host's yardstick may take (a fresh process loading MuJoCo, then 1500 steps).
HOST_TIMEOUT_S = 300


def host_world_steps_per_s(steps: int = 1500) -> float | None:
    """One in-process World's steps/s on this host now, from ``python -m bench.host``: a process configured as every
    swimm process is, so the yardstick does not depend on this one's environment. None, said in a warning, if it
    cannot be measured: the benchmark's result, minutes of work, is kept either way."""
    command = [sys.executable, "-m", "bench.host", str(steps)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=HOST_TIMEOUT_S, env=child_environment())
        if done.returncode == 0:
            return float(done.stdout.split()[-1])
        problem = done.stderr[-3000:]
    except (ValueError, IndexError, subprocess.TimeoutExpired) as exc:
        problem = str(exc)
    log.warning("the result carries no host_world_steps_per_s, the measurement failed:\n%s", problem)
    return None


def with_host_figure(about: dict) -> dict:
    """A provenance with the host's World steps/s: ``about`` itself where it has the figure (or says why not, as a
    merge's null does), else a copy with it measured now."""
    if HOST_FIGURE in about:
        return about
    return {**about, HOST_FIGURE: host_world_steps_per_s()}


def measure(steps: int) -> float:
    """``steps`` random actions of a warmed-up World, in this process as it is configured."""
    with ExitStack() as stack:
        tally = Tally()
        step_inprocess(warm_world(stack), random_actions(steps, seed=2), tally)
    return round(tally.rate, 1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="one in-process World's steps/s (64x64 frames) on this host")
    parser.add_argument("steps", type=int, nargs="?", default=1500)
    steps = parser.parse_args(argv).steps
    if steps < 1:
        parser.error(f"steps must be at least 1, got {steps}")
    configure_process(ProcessSettings(render_threads=DEFAULT_RENDER_THREADS), role="host yardstick")
    sys.stdout.write(f"{measure(steps)}\n")


if __name__ == "__main__":
    main()
