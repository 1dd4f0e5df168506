"""A virtual LAN of Linux network namespaces: each host its own namespace and address, joined by a bridge.

The bridge lives in a namespace of its own (the "switch"), so the test's own namespace is not on the LAN
and every service reaches the others only through its veth "cable". Pulling a cable is
``ip link set <port> down`` on the switch side: the host keeps its address, its TCP connections just go
silent, as when a machine drops off the network.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from services.procs import ProcessGroup, Service

SUBNET = "10.77.0"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


def netns_unavailable_reason() -> str | None:
    """Why this machine cannot run namespace tests, or None when it can."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    probe = f"swimm-probe-{uuid.uuid4().hex[:6]}"
    try:
        _ip("netns", "add", probe)
        _ip("netns", "del", probe)
    except subprocess.CalledProcessError as exc:
        return f"`ip netns add` failed: {exc.stderr.strip()}"
    return None


@dataclass
class VirtualLan:
    """Hosts on ``10.77.0.0/24``; ``add_host`` gives each the next address, starting at .1."""

    tag: str = field(default_factory=lambda: uuid.uuid4().hex[:5])
    hosts: dict[str, str] = field(default_factory=dict)  # host name -> address
    ports: dict[str, str] = field(default_factory=dict)  # host name -> its cable's end in the switch
    created: list[str] = field(default_factory=list)  # namespaces to delete at close, the switch first

    def __post_init__(self) -> None:
        self.switch = f"swimm-{self.tag}-lan"
        _ip("netns", "add", self.switch)
        self.created.append(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")

    def namespace(self, host: str) -> str:
        return f"swimm-{self.tag}-{host}"

    def add_host(self, host: str) -> str:
        """Create ``host``'s namespace, cable it to the switch, and return its address."""
        ns, port = self.namespace(host), f"p{self.tag}{len(self.ports)}"
        address = f"{SUBNET}.{len(self.hosts) + 1}"
        _ip("netns", "add", ns)
        self.created.append(ns)
        _ip("link", "add", port, "type", "veth", "peer", "name", f"{port}h")
        _ip("link", "set", port, "netns", self.switch)
        _ip("link", "set", f"{port}h", "netns", ns)
        _ip("-n", self.switch, "link", "set", port, "master", "br0", "up")
        _ip("-n", ns, "link", "set", f"{port}h", "name", "eth0")
        _ip("-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
        _ip("-n", ns, "link", "set", "eth0", "up")
        _ip("-n", ns, "link", "set", "lo", "up")
        self.hosts[host], self.ports[host] = address, port
        return address

    def cut(self, host: str) -> None:
        """Pull ``host``'s cable at the switch."""
        _ip("-n", self.switch, "link", "set", self.ports[host], "down")

    def start(self, group: ProcessGroup, host: str, name: str, argv: list[str]) -> Service:
        """Run ``python <argv>`` inside ``host``'s namespace as one of ``group``'s processes (stopped at teardown)."""
        group.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = Path(group.log_dir) / f"{name}.log"
        env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **group.env}
        with open(log_path, "ab") as log_file:
            # `ip netns exec` execs the command, so the pid (and its signals) are the service's own.
            process = subprocess.Popen(
                ["ip", "netns", "exec", self.namespace(host), sys.executable, *argv],
                stdout=log_file,
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
            )
        service = Service(name, process, log_path)
        group.services.append(service)
        return service

    def close(self) -> None:
        for ns in self.created:  # deleting a namespace deletes the veth ends inside it
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
