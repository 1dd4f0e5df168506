"""`swimm status` against a real router, sim and learner-side session: the roster, rates and envs it reports."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import pytest

from services.presence import process_of
from tests.integration.conftest import start_sim
from tests.integration.test_sim_over_zenoh import actions, remote_episode

pytestmark = pytest.mark.slow


def status(endpoint: str, namespace: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "swimm", "status", "--connect", endpoint, "--namespace", namespace, *extra],
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
    assert roles["learner"]["id"] == process_of(client.holder)  # the test's process, holding train/0
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


def test_a_learner_process_is_one_row_with_its_phase_steps_and_evaluation(group, namespace, tmp_path) -> None:
    """A real `swimm learn` process claims a train and an eval env (two holder ids): status shows it once, with
    what it is doing from the numbers it publishes."""
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", "1", "--eval-envs", "1")
    run_dir = tmp_path / "run"
    learner = group.start("learner", "learn", "--connect", endpoint, "--namespace", namespace, "--obs", "state",
                          "--run-dir", str(run_dir), "--steps", "100000", "--max-steps", "100", "--hyperparams",
                          "{learning_starts: 50, gradient_steps: 1, batch_size: 32, buffer_size: 2000}",
                          "--eval-min-steps", "100", "--eval-every", "1", "--eval-episodes", "1",
                          "--eval-max-steps", "50")  # fmt: skip
    deadline = time.monotonic() + 120
    while not (run_dir / "evaluations.csv").is_file():
        assert learner.alive and time.monotonic() < deadline, learner.log_tail(40)
        time.sleep(0.5)
    result = status(endpoint, namespace, "--json")
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout)
    learners = [entry for entry in report["services"] if entry["role"] == "learner"]
    assert len(learners) == 1, report["services"]
    (row,) = learners
    assert len(row["members"]) == 2 and all(process_of(member) == row["id"] for member in row["members"])
    assert {env["holder"] for env in report["envs"]} == set(row["members"])  # train/0 and eval/0
    counters = row["counters"]
    assert counters["phase"] in ("training", "evaluation") and counters["num_timesteps"] >= 100
    assert counters["eval_timesteps"] >= 100 and "eval " in row["doing"]
    text = status(endpoint, namespace, "--window-s", "2.5").stdout
    assert text.count("learner-") == 1 + 2  # its row, and the two envs it holds
