"""The host's yardstick, one in-process World's steps/s (64x64 frames), measured in a process of its own.

Every committed speed figure carries it, since hosts here differ by up to 2x. Mesa fixes its rasteriser threads
(``LP_NUM_THREADS``) at a process's first frame, and at 64x64 its default of one thread per core renders about half
as fast as drawing on the stepping thread, which every swimm process does: measured in the caller's process the
yardstick would depend on how the caller happened to start. ``python -m bench.host [STEPS]`` prints it, and every
benchmark's ``--json`` runs it for its provenance (bench/command.py).
"""

from __future__ import annotations

import argparse
import sys
from contextlib import ExitStack

from bench.sim import Tally, random_actions, step_inprocess, warm_world
from services.process import DEFAULT_RENDER_THREADS, ProcessSettings, configure_process


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
