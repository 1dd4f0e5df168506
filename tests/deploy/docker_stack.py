"""Docker for the compose test: a base image made without a registry, the two swimm images, and a compose project.

The base image is debootstrapped Debian (deploy/make-base-image.sh) kept under a fixed tag, so only the
first run on a machine pays for it; the swimm images are built on it with the layer cache, so a run that
changed only source files rebuilds only their last layer. Build times are kept for the report.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
BASE_TAG = os.environ.get("SWIMM_TEST_BASE_IMAGE", "swimm-test-base:bookworm")
SIM_TAG = "swimm-sim:test"
TORCH_TAG = "swimm-torch:test"
LOCAL_CA_DIR = Path("/usr/local/share/ca-certificates")
CPU_TORCH_INDEX = "https://download.pytorch.org/whl/cpu"


def run(*args: str, timeout_s: float = 900, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run a command; on failure raise with its own output, which says what went wrong."""
    result = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, env=env)
    if result.returncode != 0:
        output = result.stdout[-3000:] + result.stderr[-3000:]
        raise RuntimeError(f"{' '.join(args)} failed ({result.returncode}):\n{output}")
    return result


def docker_unavailable_reason() -> str | None:
    if shutil.which("docker") is None:
        return "no docker command"
    if subprocess.run(["docker", "info"], capture_output=True).returncode != 0:
        return "`docker info` fails: no Docker engine reachable"
    if not compose_command():
        return "neither `docker compose` nor `docker-compose` is installed"
    return None


def compose_command() -> list[str]:
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return ["docker-compose"] if shutil.which("docker-compose") else []


def image_exists(tag: str) -> bool:
    return subprocess.run(["docker", "image", "inspect", tag], capture_output=True).returncode == 0


def base_image_unavailable_reason() -> str | None:
    """None when the base image exists or can be made here (root and debootstrap)."""
    if image_exists(BASE_TAG):
        return None
    if os.geteuid() != 0 or shutil.which("debootstrap") is None:
        return f"no {BASE_TAG} image, and making one needs root and debootstrap (apt-get install debootstrap)"
    return None


def torch_index_url() -> str:
    """PyTorch's CPU-only index (small) when this machine can reach it, else "" for pip's own index (CUDA torch)."""
    if url := os.environ.get("SWIMM_TEST_TORCH_INDEX_URL"):
        return url
    try:
        socket.getaddrinfo("download.pytorch.org", 443)
        return CPU_TORCH_INDEX
    except OSError:
        return ""


def extra_ca_certs() -> str:
    """This machine's locally added CA certificates (a TLS-intercepting proxy's), for pip inside the build."""
    return "".join(path.read_text() for path in sorted(LOCAL_CA_DIR.glob("*.crt")))


@dataclass
class Images:
    timings_s: dict[str, float] = field(default_factory=dict)

    def build(self) -> None:
        if not image_exists(BASE_TAG):
            self._timed("base image (debootstrap)", "bash", str(DEPLOY / "make-base-image.sh"), BASE_TAG)
        args = ["--build-arg", f"BASE_IMAGE={BASE_TAG}", "--build-arg", f"TORCH_INDEX_URL={torch_index_url()}"]
        if extra_ca_certs():
            args += ["--build-arg", f"EXTRA_CA_CERTS={extra_ca_certs()}"]
        for tag, dockerfile in ((SIM_TAG, "Dockerfile.sim"), (TORCH_TAG, "Dockerfile.torch")):
            dockerfile_path = str(DEPLOY / dockerfile)
            self._timed(f"{tag} build", "docker", "build", "-q", "-f", dockerfile_path, *args, "-t", tag, str(REPO))

    def _timed(self, what: str, *args: str) -> None:
        start = time.monotonic()
        run(*args, timeout_s=1800)
        self.timings_s[what] = round(time.monotonic() - start, 1)


def running_containers(*labels: str) -> list[str]:
    """Ids of the running containers that carry every one of ``labels`` (``key=value``)."""
    filters = [arg for label in labels for arg in ("--filter", f"label={label}")]
    return run("docker", "ps", "-q", "--no-trunc", *filters).stdout.split()


@dataclass
class ComposeProject:
    """One `docker compose` project of deploy/docker-compose.yml, configured by environment variables."""

    env: dict[str, str]
    name: str = field(default_factory=lambda: f"swimmtest{uuid.uuid4().hex[:6]}")
    folder: Path = REPO  # where the test keeps the project's mounted models/ and runs/
    endpoint: str = ""  # the router as the host reaches it

    def __call__(self, *args: str, timeout_s: float = 300) -> subprocess.CompletedProcess:
        command = [*compose_command(), "-p", self.name, "-f", str(DEPLOY / "docker-compose.yml"), *args]
        return run(*command, timeout_s=timeout_s, env={**os.environ, **self.env})

    def containers(self, service: str) -> list[str]:
        """Ids of the service's running containers."""
        return running_containers(f"com.docker.compose.project={self.name}", f"com.docker.compose.service={service}")

    def health(self, container: str) -> str:
        return run("docker", "inspect", "-f", "{{.State.Health.Status}}", container).stdout.strip()

    def logs(self) -> str:
        try:
            return self("logs", "--no-color", "--tail", "40").stdout
        except RuntimeError as exc:
            return str(exc)

    def down(self) -> None:
        try:
            self("down", "-v", "--remove-orphans", "-t", "5", timeout_s=120)
        except RuntimeError:
            pass  # the project may never have come up


@dataclass
class SwarmStack:
    """One `docker stack deploy` of deploy/docker-stack.yml, configured by environment variables."""

    env: dict[str, str]
    endpoint: str = ""  # the router as the host reaches it
    name: str = field(default_factory=lambda: f"swimmtest{uuid.uuid4().hex[:6]}")

    def deploy(self) -> None:
        # --resolve-image never: the images are this machine's own, in no registry.
        run("docker", "stack", "deploy", "--resolve-image", "never", "-c", str(DEPLOY / "docker-stack.yml"),
            self.name, env={**os.environ, **self.env})  # fmt: skip

    def containers(self, service: str) -> list[str]:
        """Ids of the service's running containers."""
        return running_containers(f"com.docker.swarm.service.name={self.name}_{service}")

    def logs(self) -> str:
        tasks = run("docker", "stack", "ps", "--no-trunc", self.name).stdout
        tails = []
        for service in ("router", "sim", "encoder", "learner"):
            result = subprocess.run(["docker", "service", "logs", "--tail", "15", f"{self.name}_{service}"],
                                    capture_output=True, text=True, timeout=60)  # fmt: skip
            tails.append(f"--- {service}\n{result.stdout[-2000:]}{result.stderr[-1000:]}")
        return tasks + "\n".join(tails)

    def remove(self) -> None:
        subprocess.run(["docker", "stack", "rm", self.name], capture_output=True, timeout=120)
        deadline = time.monotonic() + 120  # rm returns at once; the containers and the network go after
        while time.monotonic() < deadline:
            left = run("docker", "ps", "-aq", "--filter", f"label=com.docker.stack.namespace={self.name}").stdout
            networks = run("docker", "network", "ls", "-q", "--filter", f"label=com.docker.stack.namespace={self.name}")
            if not left.strip() and not networks.stdout.strip():
                return
            time.sleep(1.0)


def swarm_state() -> str:
    """This engine's Swarm state: "active" when it is a node of a swarm, else "inactive" (or "pending", "error")."""
    return run("docker", "info", "--format", "{{.Swarm.LocalNodeState}}").stdout.strip()
