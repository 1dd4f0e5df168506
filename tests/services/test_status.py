"""`swimm status` with no router: one line and exit 1 within seconds, not a minute of retries."""

from __future__ import annotations

import subprocess
import sys
import time


def test_status_without_a_router_says_so_in_one_line_within_5_s(free_port) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "swimm", "status", "--connect", endpoint],
                            capture_output=True, text=True, timeout=30)  # fmt: skip
    assert time.monotonic() - started < 5
    assert result.returncode == 1 and result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"no Zenoh router answered at {endpoint} within 2 s")
    assert "--wait-s" in lines[0] and ".rs:" not in lines[0]


def test_wait_s_waits_as_long_as_asked(free_port) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "swimm", "status", "--connect", endpoint, "--wait-s", "4"],
                            capture_output=True, text=True, timeout=30)  # fmt: skip
    assert 2 < time.monotonic() - started < 8 and result.returncode == 1  # retries stop before a wait past 4 s
    assert "within 4 s" in result.stderr
