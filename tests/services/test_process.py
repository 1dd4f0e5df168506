"""services/process.py: `swimm`'s main sets the process-wide settings (switch interval, ZENOH_RUNTIME,
LP_NUM_THREADS) from its command's settings before the command runs, says so in one line, and the processes it
starts do not see them; library code (a World) sets none of them."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from services.process import ProcessSettings, zenoh_runtime
from services.router import RouterSettings
from sim_service.settings import SimSettings, WorldSettings

#: `swimm <argv>` with the command's run replaced by one that reports what the process looks like then, and what a
#: process it starts (through services.procs' environment) sees.
WHAT_A_COMMAND_RUNS_WITH = """
import dataclasses, json, os, subprocess, sys
from swimm import cli
from services.process import child_environment

seen = {}

def report(settings):
    child = subprocess.run(
        [sys.executable, "-c", "import json, os, sys; print(json.dumps([os.environ.get(n) for n in sys.argv[1:]]))",
         "ZENOH_RUNTIME", "LP_NUM_THREADS"],
        env=child_environment(), capture_output=True, text=True, check=True,
    )
    seen.update(switch=sys.getswitchinterval(), zenoh=os.environ.get("ZENOH_RUNTIME"),
                render=os.environ.get("LP_NUM_THREADS"), child=json.loads(child.stdout))
    return 0

command = sys.argv[1]
spec = cli.COMMANDS[command]
cli.COMMANDS[command] = dataclasses.replace(spec, load=lambda: dataclasses.replace(spec.load(), run=report))
code = cli.main(sys.argv[1:])
print(json.dumps({"code": code, **seen}))
"""


def run_swimm(*argv: str, environ: dict[str, str] | None = None) -> tuple[dict, str]:
    environment = {k: v for k, v in os.environ.items() if k not in ("ZENOH_RUNTIME", "LP_NUM_THREADS")}
    done = subprocess.run(
        [sys.executable, "-c", WHAT_A_COMMAND_RUNS_WITH, *argv],
        capture_output=True, text=True, timeout=120, env={**environment, **(environ or {})},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


def test_the_entry_point_sets_each_setting_once_from_the_commands_settings_and_logs_it():
    report, log = run_swimm("sim", "--poll-ms", "2", "--zenoh-threads", "2", "--render-threads", "3")
    assert report["code"] == 0, log[-2000:]
    assert report["switch"] == pytest.approx(2e-5)
    assert report["zenoh"] == zenoh_runtime(2)
    assert report["render"] == "3"
    assert report["child"] == [None, None]  # what the sim starts chooses for itself
    lines = [line for line in log.splitlines() if "process settings" in line]
    assert len(lines) == 1 and "ZENOH_RUNTIME" in lines[0] and "LP_NUM_THREADS=3" in lines[0], log[-2000:]


def test_the_defaults_are_the_ones_swimm_always_had():
    sim, _ = run_swimm("sim")
    assert sim["switch"] == pytest.approx(0.005)  # Python's: the sim blocks on its inbox
    assert sim["zenoh"] == zenoh_runtime(1)
    assert sim["render"] == "0"
    router, _ = run_swimm("router")
    assert (router["zenoh"], router["render"]) == (None, None)  # Zenoh's pools; it never renders


def test_a_users_own_variables_stand_and_are_passed_on():
    report, _ = run_swimm("sim", "--render-threads", "-1", environ={"ZENOH_RUNTIME": "(app: (worker_threads: 3))",
                                                                    "LP_NUM_THREADS": "2"})  # fmt: skip
    assert report["zenoh"] == "(app: (worker_threads: 3))" and report["render"] == "2"
    assert report["child"] == ["(app: (worker_threads: 3))", "2"]


def test_process_settings_are_read_from_the_settings_tree():
    sim = ProcessSettings.of(SimSettings(poll_ms=1.5, world=WorldSettings(render_threads=-1)))
    assert sim == ProcessSettings(poll_ms=1.5, zenoh_threads=1, render_threads=-1)
    assert ProcessSettings.of(RouterSettings()) == ProcessSettings(zenoh_threads=0)
    assert ProcessSettings.of(RouterSettings(), renders=True).render_threads == 0


def test_a_world_sets_no_process_setting():
    script = (
        "import os, sys; from sim_service.world import World; w = World(); w.reset(1); w.close(); "
        "print(os.environ.get('LP_NUM_THREADS'), sys.getswitchinterval())"
    )
    environment = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=environment, check=True)
    assert done.stdout.split() == ["None", "0.005"]
