"""The shipped TLS + access-control router (deploy/zenoh/router-tls-acl.json5) keeps intruders off the step pipeline.

Real processes over a real TLS router: `swimm router` started from the config, `swimm sim` and a learner
session with their own credentials. An intruder that has the encoder's credentials (a leaked password of a
service that may connect) publishes spoofed actions with the learner's name and the next sequence number
before every legitimate one, asks the sim to reset the episode, and announces itself as a learner. The
router must drop all of it, so the sim's trajectory stays the one the seed and the learner's actions give.
"""

from __future__ import annotations

import queue

import numpy as np
import pytest

from learner_service.link import EnvLink, new_holder_id
from services import control
from services.keys import Keys
from services.messages import ActionMsg, BatchItem, BatchMsg, ResetRequest, batch_messages
from services.presence import Roster, announce
from services.procs import ProcessGroup, free_tcp_port, wait_for_port
from services.session import StartupTimeout, open_session
from services.settings import ZenohSettings
from sim_service.world import World
from tests.deploy.secure_zenoh import SecureRouterFiles, make_secure_router_files

pytestmark = pytest.mark.slow
STEPS = 60
SEED = 11


def settings(files: SecureRouterFiles, namespace: str, role: str, **credentials) -> ZenohSettings:
    return ZenohSettings(
        connect=[files.endpoint],
        zenoh_config=str(files.client_config(role, **credentials)),
        namespace=namespace,
        startup_timeout_s=20.0,
    )


@pytest.fixture
def secure_router(processes: ProcessGroup, tmp_path) -> SecureRouterFiles:
    port = free_tcp_port()
    files = make_secure_router_files(tmp_path / "zenoh", port)
    router = processes.start("router", "router", "--zenoh-config", str(files.router_config), "--listen", files.endpoint)
    if not wait_for_port("127.0.0.1", port, timeout_s=20):
        pytest.fail(f"TLS router did not listen:\n{router.log_tail()}")
    return files


def reference_telemetry(actions: list[tuple[float, ...]]) -> list:
    """The same episode in-process: no network, no intruder."""
    world = World()
    try:
        return [world.reset(SEED)[0]] + [world.step(a)[0] for a in actions]
    finally:
        world.close()


def test_only_learners_drive_the_sim_behind_the_tls_acl_router(secure_router, processes, namespace):
    files = secure_router
    keys = Keys(namespace)
    processes.start(
        "sim", "sim", "--zenoh-config", str(files.client_config("sim")), "--connect", files.endpoint,
        "--namespace", namespace,
    )  # fmt: skip
    learner = open_session(settings(files, namespace, "learner"), role="learner")
    intruder = open_session(settings(files, namespace, "encoder"), role="intruder")
    sessions = [learner, intruder]
    try:
        holder = new_holder_id("learner")
        token = announce(learner, keys, "learner", holder)
        Roster(learner, keys, "sim").wait_for(1, timeout_s=60)

        # What reaches subscribers on the action key, seen by a learner-credentialed monitor.
        monitor = open_session(settings(files, namespace, "learner"), role="monitor")
        sessions.append(monitor)
        seen_actions: queue.Queue[ActionMsg] = queue.Queue()
        seen_metrics: queue.Queue[bytes] = queue.Queue()
        action_sub = monitor.declare_subscriber(
            keys.action("train", "0"),
            lambda s: [seen_actions.put(msg) for _, msg in batch_messages(s.payload.to_bytes(), ActionMsg.from_item)],
        )
        metrics_sub = monitor.declare_subscriber(keys.all_metrics(), lambda s: seen_metrics.put(bytes(s.payload)))
        learners_seen = Roster(monitor, keys, "learner")

        link = EnvLink(learner, keys, "train", ["0"], holder, encoded=False, step_timeout_s=5.0, max_retries=2)
        link.claim()
        rng = np.random.default_rng(SEED)
        actions = [tuple(float(x) for x in row) for row in rng.uniform(-1, 1, (STEPS, 4))]
        link.send_reset(1, SEED)
        telemetry = [link.wait()[0].telemetry]

        # Refused: an encoder may announce only an encoder token.
        intruder_token = announce(intruder, keys, "learner", "learner-intruder")
        with pytest.raises(control.ControlError):  # the query never reaches the sim, so nobody answers
            control.request(intruder, keys.ctl("train", "0"), ResetRequest(holder, ep=2, seed=999), 2.0)
        spoofs = intruder.declare_publisher(keys.action("train", "0"))
        for action in actions:
            # The intruder goes first each step: were it let through, the sim would apply its action as this seq.
            spoof = ActionMsg(1, link.seq[0] + 1, (1.0, 1.0, 1.0, -1.0), sender=holder)
            spoofs.put(BatchMsg.alone(BatchItem.of("0", spoof), holder).encode())
            link.send([action])
            telemetry.append(link.wait()[0].telemetry)
        intruder.put(keys.metrics("encoder", "intruder"), b"the intruder is connected and may publish metrics")

        assert telemetry == reference_telemetry(actions)  # the sim's step sequence is the intruder-free one
        assert link.retries == 0 and link.duplicates_dropped == 0
        got = []
        while len(got) < STEPS:
            got.append(seen_actions.get(timeout=10))
        assert [(m.seq, m.action) for m in got] == [(i + 1, a) for i, a in enumerate(actions)]
        assert seen_actions.empty()  # nothing but the learner's own actions crossed the router
        assert b"the intruder is connected" in seen_metrics.get(timeout=10)  # so the refusals above are the ACL's
        assert learners_seen.members() == {holder}  # the intruder's learner token was dropped too

        link.close()
        intruder_token.undeclare()
        spoofs.undeclare()
        action_sub.undeclare()
        metrics_sub.undeclare()
        token.undeclare()
    finally:
        for session in sessions:
            session.close()


def test_clients_without_valid_credentials_cannot_connect(secure_router, namespace):
    files = secure_router
    for credentials in ({"password": "not-the-password"}, {"user": "stranger", "password": "whatever"}):
        quick = settings(files, namespace, "learner", **credentials)
        quick.startup_timeout_s = 2.0
        with pytest.raises(StartupTimeout):
            open_session(quick, role="intruder")
    legit = open_session(settings(files, namespace, "learner"), role="learner")  # the router itself is up
    legit.close()
