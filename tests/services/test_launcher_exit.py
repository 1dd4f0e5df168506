"""A service whose launcher is killed outright stops by itself, instead of living on with its port and core."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.slow

LAUNCHER = """
import sys, time
from pathlib import Path
from services.procs import ProcessGroup
group = ProcessGroup(Path(sys.argv[1]))
group.start_router()
print(group.services[0].process.pid, flush=True)
time.sleep(600)
"""


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as stat:  # a zombie is gone for our purpose: it holds no port or core
        return stat.read().split(") ")[-1][0] != "Z"


def test_a_router_outlives_no_launcher_killed_with_sigkill(tmp_path) -> None:
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(tmp_path / "logs")], stdout=subprocess.PIPE,
                                text=True)  # fmt: skip
    router = int(launcher.stdout.readline())
    try:
        assert alive(router)
        launcher.send_signal(signal.SIGKILL)
        launcher.wait(timeout=10)
        deadline = time.monotonic() + 20
        while alive(router) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not alive(router), "the router kept running after its launcher was killed"
        assert "the launcher (pid" in (tmp_path / "logs" / "router.log").read_text()
    finally:
        if alive(router):
            os.kill(router, signal.SIGKILL)
