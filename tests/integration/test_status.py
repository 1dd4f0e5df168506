"""`swimm status` against a real router, sim and learner-side session: the roster, rates and envs it reports."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import pytest

from tests.integration.conftest import start_sim
from tests.integration.test_sim_over_zenoh import actions, remote_episode

pytestmark = pytest.mark.slow


def status(endpoint: str, namespace: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", "status", "--connect", endpoint, "--namespace", namespace, *extra],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def test_status_names_the_live_services_their_rates_and_who_holds_each_env(group, connect_client, namespace) -> None:
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", "1", "--eval-envs", "1")
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    link = client.link()
    link.claim()
    stepping = threading.Event()

    def step_while_status_listens() -> None:
        ep = 0
        while not stepping.is_set():
            ep += 1
            remote_episode(link, ep, 42, actions(100))

    worker = threading.Thread(target=step_while_status_listens)
    worker.start()
    try:
        result = status(endpoint, namespace, "--json")
    finally:
        stepping.set()
        worker.join()
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout)
    roles = {entry["role"]: entry for entry in report["services"]}
    assert set(roles) == {"sim", "learner"} and all(entry["live"] for entry in roles.values())
    assert roles["learner"]["id"] == client.holder
    assert roles["sim"]["rate_unit"] == "steps/s" and roles["sim"]["rate"] > 0  # it was stepping all along
    assert 0 <= roles["sim"]["last_seen_s"] < 5
    envs = {f"{env['channel']}/{env['env']}": env for env in report["envs"]}
    assert set(envs) == {"train/0", "eval/0"}
    assert envs["train/0"]["holder"] == client.holder and envs["train/0"]["ep"] >= 1
    assert envs["eval/0"]["holder"] is None and envs["train/0"]["sim"] == roles["sim"]["id"]

    text = status(endpoint, namespace, "--window-s", "0.5")
    assert text.returncode == 0
    assert f"namespace {namespace}" in text.stdout
    assert f"train/0  {roles['sim']['id']}  {client.holder}" in text.stdout
    assert "eval/0" in text.stdout and "free" in text.stdout


def test_status_of_an_empty_namespace_says_where_it_looked(group) -> None:
    endpoint = group.start_router()
    result = status(endpoint, "swimm/nobody-here", "--window-s", "0.5")
    assert result.returncode == 1
    assert f"nothing live in namespace swimm/nobody-here (connected to {endpoint}" in result.stderr
