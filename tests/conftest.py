"""Fixtures every test folder shares: free ports, a real Zenoh router process, and swimm sub-commands as processes.

Everything here starts real components (no fakes): a test that needs a
router gets ``swimm router`` in its own process on its own port, and a
namespace of its own, so tests never hear each other's traffic.
"""

from __future__ import annotations

import os
import sys
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from services import process
from services.process import DEFAULT_RENDER_THREADS, ProcessSettings, configure_process
from services.procs import ProcessGroup, Service, free_tcp_port
from services.session import open_session
from services.settings import ZenohSettings

# MuJoCo picks its GL backend at import; headless machines (CI, the device box) render through EGL.
os.environ["MUJOCO_GL"] = "egl"

#: How long a test waits for its router or a session to appear before failing, in seconds.
STARTUP_TIMEOUT_S = 20.0


@pytest.fixture(scope="session", autouse=True)
def render_threads_of_the_test_process() -> None:
    """The test process renders Worlds as `swimm sim` does: Mesa on the stepping thread (LP_NUM_THREADS=0), set
    once, as an entry point sets it (services/process.py), before any test makes a GL context."""
    configure_process(ProcessSettings(render_threads=DEFAULT_RENDER_THREADS), role="tests")


@pytest.fixture(autouse=True)
def process_settings_restored() -> Iterator[None]:
    """What a test's in-process `swimm` main (or configure_process) set for the process is undone after it, so
    the processes later tests start see the test process's own environment."""
    variables = (process.ZENOH_RUNTIME_VARIABLE, process.RENDER_THREADS_VARIABLE)
    environment = {name: os.environ.get(name) for name in variables}
    before = dict(process._ENVIRONMENT_BEFORE)
    switch_interval = sys.getswitchinterval()
    yield
    for name, value in environment.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    process._ENVIRONMENT_BEFORE.clear()
    process._ENVIRONMENT_BEFORE.update(before)
    sys.setswitchinterval(switch_interval)


@pytest.fixture
def free_port() -> Callable[[], int]:
    """Call it for a TCP port on 127.0.0.1 that nothing listens on right now (one per call)."""
    return free_tcp_port


@pytest.fixture
def processes(tmp_path) -> Iterator[ProcessGroup]:
    """The processes a test starts, with logs under ``tmp_path/logs``; all stopped (SIGTERM, then SIGKILL) at teardown.

    Teardown stops them in reverse start order, so clients go before the router they talk to.
    """
    with ProcessGroup(tmp_path / "logs") as group:
        yield group


@pytest.fixture
def spawn(processes: ProcessGroup) -> Callable[..., Service]:
    """Start any swimm sub-command as ``python -m swimm <command> <args>`` in its own process.

    Usage: ``service = spawn("sim", "--connect", endpoint, "--namespace", ns, name="sim-a")``.
    The returned :class:`services.procs.Service` has ``process`` (the Popen), ``alive`` and
    ``log_tail()`` (stdout and stderr together, from ``tmp_path/logs/<name>.log``). The process is
    stopped at teardown; stop it earlier (or crash it with ``kill=True``) with ``processes.stop(service)``.
    ``name`` defaults to the command and must be unique within a test, as it names the log file.
    """

    def start(command: str, *args: str, name: str | None = None) -> Service:
        return processes.start(name or command, command, *args)

    return start


@pytest.fixture
def zenoh_router(processes: ProcessGroup) -> str:
    """A ``swimm router`` process listening on a free local port; the value is its endpoint ``tcp/127.0.0.1:<port>``.

    Fails the test with the router's own log when it does not accept connections within 20 s.
    """
    return processes.start_router()


@pytest.fixture
def namespace() -> str:
    """A Zenoh namespace unique to this test, so concurrent or earlier tests' traffic never reaches it."""
    return f"swimm/test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def zenoh_settings(namespace: str) -> Callable[[str], ZenohSettings]:
    """Call with an endpoint for client settings connected to it, in this test's namespace."""

    def build(endpoint: str) -> ZenohSettings:
        return ZenohSettings(connect=[endpoint], namespace=namespace, startup_timeout_s=STARTUP_TIMEOUT_S)

    return build


@pytest.fixture
def zenoh_session(zenoh_settings: Callable[[str], ZenohSettings]) -> Iterator[Callable[[str], zenoh.Session]]:
    """Call with an endpoint to open a client session there; every session opened is closed at teardown."""
    opened: list[zenoh.Session] = []

    def connect(endpoint: str) -> zenoh.Session:
        session = open_session(zenoh_settings(endpoint), role="test")
        opened.append(session)
        return session

    yield connect
    for session in opened:
        session.close()


@pytest.fixture(scope="session")
def tracking_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tracking CMVAE (``--track``) from the shipped general one, its prior channel randomised: --init leaves it
    zero, and the latents must depend on the prior for a test to see it carried."""
    import torch  # here, not at the top: most tests never load torch

    from encoder_service.model import CMVAE, make_checkpoint
    from encoder_service.train import load_init_weights

    torch.manual_seed(5)
    model = CMVAE(10, "channel", track=True)
    load_init_weights(model, str(Path(__file__).parents[1] / "encoder_service/models/cmvae_general.pt"), 10)
    with torch.no_grad():
        prior_weights = model.encoder.features[0].weight[:, 3]
        prior_weights.copy_(torch.randn_like(prior_weights) * 0.5)
    path = tmp_path_factory.mktemp("tracking") / "cmvae_track.pt"
    torch.save(make_checkpoint(model.eval(), 8.0, 1, 0.0, {}), path)
    return path
