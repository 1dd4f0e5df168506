"""deploy/docker-stack.yml on a single-node Docker Swarm: the stack trains, and Swarm restarts a killed encoder.

The images are the compose test's (built here without a registry, tests/deploy/conftest.py). A swarm is made
for the test when the engine is in none (and left afterwards); the stack runs router, sim, two encoder replicas
and the learner on its overlay network; the test watches every latent through the router's port, published by
the routing mesh, kills the container of one encoder replica, and checks that Swarm starts a new replica, that
the training goes on through the live ones meanwhile and after, and that no step was lost or applied twice.
"""

from __future__ import annotations

import subprocess

import pytest

from services.keys import Keys
from services.presence import Roster
from services.procs import free_tcp_port
from services.session import open_session
from services.settings import ZenohSettings
from tests.deploy.docker_stack import Images, SwarmStack, run, swarm_state
from tests.deploy.observe import LatentLog, check_no_step_lost_or_repeated, stack_settings, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.docker, pytest.mark.timeout(2400)]
ENVS = 2
ENCODERS = 2
STEPS_BEFORE_KILL = 150
STEPS_AFTER_KILL = 300


@pytest.fixture(scope="module")
def swarm(images: Images):
    """A swarm to deploy to: this engine's own if it is in one, else one made here and left afterwards."""
    made_here = swarm_state() != "active"
    if made_here:
        try:
            run("docker", "swarm", "init", "--advertise-addr", "127.0.0.1")
        except RuntimeError as exc:
            pytest.skip(f"this Docker engine cannot start a swarm: {exc}")
    yield
    if made_here:
        subprocess.run(["docker", "swarm", "leave", "--force"], capture_output=True, timeout=120)


@pytest.fixture
def stack(swarm, tmp_path):
    port = free_tcp_port()
    settings = stack_settings(tmp_path, port, "swarm", ENVS) | {"SWIMM_ENCODERS": str(ENCODERS)}
    deployed = SwarmStack(settings, endpoint=f"tcp/127.0.0.1:{port}")
    try:
        deployed.deploy()
        yield deployed
    finally:
        deployed.remove()


def test_the_stack_trains_and_swarm_replaces_a_killed_encoder_replica(stack: SwarmStack) -> None:
    keys = Keys(stack.env["SWIMM_NAMESPACE"])
    zenoh = ZenohSettings(connect=[stack.endpoint], namespace=keys.namespace, startup_timeout_s=180)
    session = open_session(zenoh, role="observer")  # retries while the router's task starts
    latents = LatentLog(session, keys)
    encoders = Roster(session, keys, "encoder")
    try:
        wait_until(lambda: len(encoders.members()) == ENCODERS, 300, f"{ENCODERS} live encoder replicas", stack)
        wait_until(lambda: latents.steps() >= STEPS_BEFORE_KILL, 300, "training steps", stack)
        before = encoders.members()
        victim = stack.containers("encoder")[0]  # its replica's id is enc-<container host name>
        steps_at_kill = latents.steps()
        subprocess.run(["docker", "kill", victim], check=True, capture_output=True)
        wait_until(lambda: latents.steps() >= steps_at_kill + STEPS_AFTER_KILL, 300, "steps after the kill", stack)
        wait_until(lambda: len(encoders.members()) == ENCODERS and encoders.members() != before, 300,
                   "Swarm's new encoder replica", stack)  # fmt: skip
        assert f"enc-{victim[:12]}" in before and f"enc-{victim[:12]}" not in encoders.members()
        assert len(stack.containers("learner")) == 1, stack.logs()  # the learner never stopped
    finally:
        latents.close()
        session.close()
    check_no_step_lost_or_repeated(latents.snapshot(), ENVS)
