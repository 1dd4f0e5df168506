"""Opening Zenoh sessions: the bounded, logged back-off that lets services start in any order."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from services.router import RouterSettings
from services.session import PEER_LISTEN, StartupTimeout, build_config, endpoints, open_session
from services.settings import LOCAL_ROUTER, ZenohSettings


def test_no_router_raises_startup_timeout_within_the_bound(free_port):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = ZenohSettings(connect=[endpoint], startup_timeout_s=1.0)
    started = time.monotonic()
    with pytest.raises(StartupTimeout) as refused:
        open_session(settings, role="encoder")
    elapsed = time.monotonic() - started
    message = str(refused.value)
    assert 0.5 < elapsed <= 1.0 + 0.5  # never waits past the timeout (plus one open attempt)
    assert f"encoder could not reach a Zenoh router at {endpoint} within 1 s" in message
    assert "Is `swimm router` (or `swimm up`) running?" in message and ".rs:" not in message  # no Rust source path
    attempts = int(re.search(r"\((\d+) attempts\)", message).group(1))
    assert attempts >= 4  # back-off of 0.1, 0.2, 0.4 s fits four tries into 1 s


def test_waiting_is_logged_once_and_each_attempt_at_debug(free_port, caplog):
    settings = ZenohSettings(connect=[f"tcp/127.0.0.1:{free_port()}"], startup_timeout_s=0.5)
    with caplog.at_level("DEBUG", logger="services.session"), pytest.raises(StartupTimeout):
        open_session(settings, role="sim")
    waits = [r for r in caplog.records if "for a Zenoh router" in r.getMessage()]
    assert len(waits) >= 2
    assert waits[0].getMessage().startswith("sim waiting up to 0.5 s for a Zenoh router at tcp/127.0.0.1:")
    assert "(attempt 1)" in waits[0].getMessage() and "(attempt 2)" in waits[1].getMessage()
    assert [r.levelname for r in waits[:2]] == ["INFO", "DEBUG"]


def test_a_client_started_before_its_router_joins_once_the_router_listens(free_port, processes):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    opened: list[zenoh.Session] = []
    client = threading.Thread(
        target=lambda: opened.append(open_session(ZenohSettings(connect=[endpoint], startup_timeout_s=20.0)))
    )
    started = time.monotonic()
    client.start()
    time.sleep(1.0)
    assert not opened  # still waiting: nothing listens yet
    processes.start_router(port)
    client.join(timeout=20.0)
    assert len(opened) == 1
    session = opened[0]
    try:
        assert time.monotonic() - started < 1.0 + 10.0  # router start-up plus at most one 2 s back-off step
        assert len(list(session.info.routers_zid())) == 1
    finally:
        session.close()


def test_client_config_has_explicit_endpoints_and_no_multicast_scouting():
    config = build_config(ZenohSettings(connect=["tcp/10.1.2.3:7447", "tcp/10.1.2.4:7447"]))
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.1.2.3:7447", "tcp/10.1.2.4:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False


def test_low_latency_asks_for_that_transport_without_qos_or_shared_memory_and_lets_one_of_two_peers_dial():
    config = build_config(ZenohSettings(mode="peer", low_latency=True))
    assert json.loads(config.get_json("transport/unicast/lowlatency")) is True
    assert json.loads(config.get_json("transport/unicast/qos/enabled")) is False  # Zenoh refuses both at once
    assert json.loads(config.get_json("transport/shared_memory/enabled")) is False  # slower for lock-step frames
    strategy = json.loads(config.get_json("scouting/gossip/autoconnect_strategy"))
    assert strategy["peer"] == {"to_router": "always", "to_peer": "greater-zid"}
    standard = build_config(ZenohSettings(mode="peer"))
    assert json.loads(standard.get_json("transport/unicast/lowlatency")) is False
    assert json.loads(standard.get_json("transport/shared_memory/enabled")) is True


ZENOH_THREADS_OF_A_PROCESS = """
import glob, json, os, re, subprocess, sys, time
from services.process import ProcessSettings, child_environment, configure_process
from services.session import open_session
from services.settings import ZenohSettings

endpoint, threads = sys.argv[1], int(sys.argv[2])
configure_process(ProcessSettings.of(ZenohSettings(zenoh_threads=threads)))  # as an entry point does
listener = open_session(ZenohSettings(mode="peer", listen=[endpoint], zenoh_threads=threads))
dialler = open_session(ZenohSettings(mode="peer", connect=[endpoint], zenoh_threads=threads))
received = []
subscriber = listener.declare_subscriber("swimm/test-threads", lambda sample: received.append(1))
deadline = time.monotonic() + 10
while not received and time.monotonic() < deadline:  # until a message has crossed the link
    dialler.put("swimm/test-threads", b"x")
    time.sleep(0.05)
names = [open(task + "/comm").read().strip() for task in glob.glob("/proc/self/task/*")]
pools = sorted({name.split("-")[0] for name in names if re.fullmatch(r"(app|acc|tx|rx|net)-[0-9]+", name)})
child = subprocess.run([sys.executable, "-c", "import os; print('ZENOH_RUNTIME' in os.environ)"],
                       env=child_environment(), capture_output=True, text=True, check=True)
print(json.dumps({"received": bool(received), "pools": pools, "passed_on": child.stdout.strip() == "True"}))
subscriber.undeclare()
dialler.close()
listener.close()
"""


@pytest.mark.parametrize("threads", [1, 0])
def test_zenoh_runs_on_the_threads_asked_for_and_does_not_pass_them_on(free_port, threads):
    """Zenoh's threads, by name: one pool ('app') for every runtime, or with 0 a pool per runtime; and
    the environment variable that chose it (set by the process's entry point) is not in the environment of the
    processes it starts, so they choose for themselves."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    environment = {key: value for key, value in os.environ.items() if key != "ZENOH_RUNTIME"}
    done = subprocess.run(
        [sys.executable, "-c", ZENOH_THREADS_OF_A_PROCESS, endpoint, str(threads)],
        capture_output=True, text=True, timeout=60, env=environment,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["received"] and not report["passed_on"]
    if threads:
        assert report["pools"] == ["app"]
    else:
        assert len(report["pools"]) > 1 and "rx" in report["pools"]


def test_a_negative_thread_count_is_refused_by_name():
    with pytest.raises(ValueError, match=r"--zenoh-threads must be >= 0"):
        open_session(ZenohSettings(mode="peer", zenoh_threads=-1))


def test_router_config_listens_and_connects_nowhere():
    settings = RouterSettings(listen=["tcp/0.0.0.0:7447"]).zenoh()  # what `swimm router` opens
    assert (settings.mode, settings.connect) == ("router", [])
    config = build_config(settings)
    assert json.loads(config.get_json("mode")) == "router"
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]


def test_settings_override_a_zenoh_config_file(tmp_path):
    config_file = tmp_path / "zenoh.json5"
    config_file.write_text('{ mode: "peer", connect: { endpoints: ["tcp/192.168.0.9:7447"] }, /* a comment */ }')
    config = build_config(ZenohSettings(mode="client", connect=["tcp/10.0.0.1:7447"], zenoh_config=str(config_file)))
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]


def test_without_flags_a_config_files_endpoints_hold_and_without_either_the_local_router(tmp_path):
    router_file = tmp_path / "router.json5"
    router_file.write_text('{ listen: { endpoints: ["tls/0.0.0.0:7447"] } }')
    client_file = tmp_path / "client.json5"
    client_file.write_text('{ connect: { endpoints: ["tls/router.lan:7447"] } }')
    site_router = build_config(RouterSettings(zenoh_config=str(router_file)).zenoh())
    assert endpoints(site_router, "listen") == ["tls/0.0.0.0:7447"]
    assert endpoints(build_config(ZenohSettings(zenoh_config=str(client_file)))) == ["tls/router.lan:7447"]
    assert endpoints(build_config(RouterSettings().zenoh()), "listen") == [LOCAL_ROUTER]
    assert endpoints(build_config(ZenohSettings())) == [LOCAL_ROUTER]
    assert endpoints(build_config(RouterSettings().zenoh())) == []  # a router connects to no one unless told


def test_a_missing_zenoh_config_file_fails_at_once_naming_the_file(tmp_path):
    missing = tmp_path / "absent.json5"
    started = time.monotonic()
    with pytest.raises(Exception) as failed:  # noqa: B017 - the type is the code's choice; the message is the point
        open_session(ZenohSettings(zenoh_config=str(missing), startup_timeout_s=1.0))
    assert time.monotonic() - started < 0.3
    assert str(missing) in str(failed.value)


def test_a_peer_listens_on_a_loopback_port_unless_given_its_own_endpoints():
    assert endpoints(build_config(ZenohSettings(mode="peer")), "listen") == [PEER_LISTEN]
    given = build_config(ZenohSettings(mode="peer", listen=["tcp/0.0.0.0:7450"]))
    assert endpoints(given, "listen") == ["tcp/0.0.0.0:7450"]
    assert json.loads(build_config(ZenohSettings()).get_json("listen/endpoints")) != [PEER_LISTEN]  # a client's


def test_peers_the_router_introduced_keep_talking_directly_when_it_is_gone(free_port, processes):
    """What `swimm up` relies on: peers that only know the router link to each other, and their messages skip it."""
    endpoint = processes.start_router(free_port())
    peer_a, peer_b = (open_session(ZenohSettings(mode="peer", connect=[endpoint]), role="peer") for _ in range(2))
    try:
        deadline = time.monotonic() + 10
        while peer_b.info.zid() not in list(peer_a.info.peers_zid()):
            assert time.monotonic() < deadline, "the peers never linked directly"
            time.sleep(0.05)
        received: list[bytes] = []
        key = "swimm/test-peers/frame"
        subscriber = peer_b.declare_subscriber(key, lambda sample: received.append(sample.payload.to_bytes()))
        time.sleep(0.3)  # the subscription reaches peer_a
        processes.stop(processes.services[0])  # the router
        peer_a.put(key, b"direct")
        deadline = time.monotonic() + 5
        while not received and time.monotonic() < deadline:
            time.sleep(0.02)
        assert received == [b"direct"]
        subscriber.undeclare()
    finally:
        peer_a.close()
        peer_b.close()
