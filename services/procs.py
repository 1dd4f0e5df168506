"""Start swimm services as separate local processes and stop them cleanly.

Used by `swimm up` (the embedded default system), the benchmarks (which
must measure real processes talking over a real router) and the
integration tests. Each service is ``python -m swimm <command> ...``
with its log in a file, so a failure can be shown with its own words.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from services.lifecycle import LAUNCHER_PID_ENV
from services.process import child_environment
from services.settings import SETTINGS_EXIT_CODE

log = logging.getLogger(__name__)


def zenoh_flags(low_latency: bool, zenoh_threads: int | None = None) -> tuple[str, ...]:
    """The flags that give a started swimm process Zenoh's low-latency setting (``ZenohSettings.low_latency``)
    and, unless None, its number of Zenoh threads (``ZenohSettings.zenoh_threads``).

    A link uses the low-latency transport only when both its ends ask for it, so whoever starts a set of
    processes passes the same setting to each of them, the router included; the router keeps its own thread
    count (see ``services.router.RouterSettings``).
    """
    threads = () if zenoh_threads is None else ("--zenoh-threads", str(zenoh_threads))
    return (*(("--low-latency",) if low_latency else ()), *threads)


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for_port(host: str, port: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            time.sleep(0.05)
    return False


@dataclass
class Service:
    name: str
    process: subprocess.Popen
    log_path: Path
    argv: tuple[str, ...] = ()  # the command line it was started with, to start it again
    restarts: int = 0  # times it was started again after it died

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    @property
    def refused_settings(self) -> bool:
        """It exited refusing its settings: started again, it would refuse them again, so it never is."""
        return self.process.poll() == SETTINGS_EXIT_CODE


@dataclass
class ProcessGroup:
    """A set of swimm processes sharing a log directory; stops them all (SIGTERM, then SIGKILL) on exit."""

    log_dir: Path
    env: dict[str, str] = field(default_factory=dict)
    services: list[Service] = field(default_factory=list)

    def start(self, name: str, command: str, *args: str) -> Service:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        argv = (sys.executable, "-m", "swimm", command, *args)
        service = Service(name, self._spawn(argv, self.log_dir / f"{name}.log"), self.log_dir / f"{name}.log", argv)
        self.services.append(service)
        log.info("started %s (pid %d), log %s", name, service.process.pid, service.log_path)
        return service

    def restart(self, service: Service) -> None:
        """Start a dead service again with its command line, its log appended to (compose's ``restart``)."""
        if service.alive:
            raise RuntimeError(f"{service.name} is running (pid {service.process.pid}); stop it before a restart")
        if service.refused_settings:
            raise RuntimeError(f"{service.name} refused its settings; started again it would refuse them again")
        code = service.process.returncode
        with open(service.log_path, "a") as log_file:
            log_file.write(f"\n--- swimm up: {service.name} exited with {code}; started again ---\n")
        service.process = self._spawn(service.argv, service.log_path)
        service.restarts += 1
        log.warning("%s exited with %s: restarted (pid %d, restart %d)", service.name, code, service.process.pid,
                    service.restarts)  # fmt: skip

    def _spawn(self, argv: Sequence[str], log_path: Path) -> subprocess.Popen:
        # child_environment: without the process-wide settings this process set for itself (services/process.py);
        # each child sets its own from its flags.
        env = {**child_environment(), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **self.env,
               LAUNCHER_PID_ENV: str(os.getpid())}  # fmt: skip
        with open(log_path, "ab") as log_file:
            return subprocess.Popen(
                list(argv),
                stdout=log_file,
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,  # a Ctrl-C in the terminal reaches us; we stop children in order
            )

    def start_router(self, port: int | None = None, name: str = "router", flags: Sequence[str] = ()) -> str:
        """Start `swimm router` on a port (with more ``flags``) and wait until it accepts connections; returns its
        endpoint."""
        port = port or free_tcp_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        service = self.start(name, "router", "--listen", endpoint, *flags)
        if not wait_for_port("127.0.0.1", port, timeout_s=20):
            raise RuntimeError(f"router did not listen on {endpoint} within 20 s:\n{service.log_tail()}")
        return endpoint

    def stop(self, service: Service, timeout_s: float = 15.0, kill: bool = False) -> int:
        """Stop one service: SIGTERM (drain and exit) or SIGKILL (a crash); returns its exit code."""
        if service.alive:
            service.process.send_signal(signal.SIGKILL if kill else signal.SIGTERM)
        try:
            return service.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("%s ignored SIGTERM for %.0f s; killing it", service.name, timeout_s)
            service.process.kill()
            return service.process.wait()

    def check_alive(self) -> None:
        for service in self.services:
            if not service.alive:
                raise RuntimeError(f"{service.name} exited with {service.process.returncode}:\n{service.log_tail()}")

    def close(self) -> None:
        for service in reversed(self.services):  # clients first, the router last
            self.stop(service)

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
