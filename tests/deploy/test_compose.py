"""deploy/docker-compose.yml end to end: images built here without a registry, training, scaling, a killed encoder.

The images are built on a debootstrapped base (tests/deploy/docker_stack.py). The stack runs router, sim,
one encoder and the learner; the test watches the step pipeline from outside, through the router's
published port, recording every latent's (env, ep, seq, sim clock, encoder). It scales the encoders to 3
while training runs, kills the container of an encoder that is serving envs, and checks that training
goes on: those envs move to live encoders, and every episode seen is whole (seq 0, 1, 2, ... with no gap)
with the sim's clock at seq * physics_dt at each step, so no step was lost or applied twice.
Then the eval profile attaches to the same live sim and writes its report.
"""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from services.keys import Keys
from services.presence import Roster
from services.procs import free_tcp_port
from services.session import open_session
from services.settings import ZenohSettings
from tests.deploy.docker_stack import ComposeProject, Images
from tests.deploy.observe import LatentLog, check_no_step_lost_or_repeated, stack_settings, wait_until

pytestmark = [
    pytest.mark.slow,
    pytest.mark.docker,
    # The first run on a machine builds the images (the torch image's pip install alone takes minutes).
    pytest.mark.timeout(2400),
]
ENVS = 2
STEPS_BEFORE_SCALING = 150
STEPS_AFTER_KILL = 300


@pytest.fixture(scope="module")
def stack(images: Images, tmp_path_factory):
    folder = tmp_path_factory.mktemp("compose")
    port = free_tcp_port()
    project = ComposeProject(
        stack_settings(folder, port, "compose", ENVS) | {"SWIMM_CHECKPOINT_EVERY": "200"},
        folder=folder,
        endpoint=f"tcp/127.0.0.1:{port}",
    )
    try:
        project("up", "-d", "--no-build", "router")
        yield project
    finally:
        project.down()


def test_training_goes_on_when_encoders_scale_and_one_is_killed(stack: ComposeProject) -> None:
    keys = Keys(stack.env["SWIMM_NAMESPACE"])
    session = open_session(ZenohSettings(connect=[stack.endpoint], namespace=keys.namespace), role="observer")
    latents = LatentLog(session, keys)
    encoders = Roster(session, keys, "encoder")
    try:
        started = time.monotonic()
        stack("up", "-d", "--no-build", "sim", "encoder", "learner")
        wait_until(lambda: latents.steps() >= STEPS_BEFORE_SCALING, 300, "training steps through one encoder", stack)
        progress = stack.folder / "runs" / "train" / "progress.json"
        wait_until(progress.exists, 120, "the learner's progress.json", stack)
        first_steps_s = time.monotonic() - started

        stack("up", "-d", "--no-build", "--no-recreate", "--scale", "encoder=3", "encoder")
        wait_until(lambda: len(encoders.members()) == 3, 180, "three live encoders", stack)
        for container in stack.containers("encoder"):
            wait_until(lambda c=container: stack.health(c) == "healthy", 120, f"{container[:12]} healthy", stack)

        # Kill an encoder that is serving envs right now (its id is enc-<container host name>).
        recent = latents.snapshot()[-ENVS * 5 :]
        victim = recent[-1][4]
        victim_envs = {row[0] for row in recent if row[4] == victim}
        container = next(c for c in stack.containers("encoder") if victim == f"enc-{c[:12]}")
        steps_at_kill, rows_at_kill = latents.steps(), len(latents.snapshot())
        killed_at = time.monotonic()
        subprocess.run(["docker", "kill", container], check=True, capture_output=True)
        wait_until(lambda: latents.steps() >= steps_at_kill + STEPS_AFTER_KILL, 300, "steps after the kill", stack)
        recovered_s = time.monotonic() - killed_at
        assert victim not in encoders.members() and len(encoders.members()) == 2
        for name in ("learner", "sim"):
            assert all(stack.health(c) == "healthy" for c in stack.containers(name)), stack.logs()
    finally:
        latents.close()
        session.close()

    rows = latents.snapshot()
    late = rows[rows_at_kill:][-ENVS * 50 :]  # the last steps: every env steps, none through the dead encoder
    assert {row[0] for row in late} == {str(i) for i in range(ENVS)}
    assert victim not in {row[4] for row in late}
    assert victim_envs <= {row[0] for row in late}  # the victim's envs moved to live encoders
    check_no_step_lost_or_repeated(rows, ENVS)
    report = {"first_steps_s": round(first_steps_s, 1), "recovered_s": round(recovered_s, 1), "steps": len(rows)}
    (stack.folder / "compose-timings.json").write_text(json.dumps(report))


def test_the_eval_profile_attaches_to_the_live_sim_and_reports(stack: ComposeProject) -> None:
    saved = (stack.folder / "runs" / "train" / "checkpoints").glob("*.zip")
    checkpoints = sorted(saved, key=lambda path: path.stat().st_mtime)
    assert checkpoints, "the learner wrote no checkpoint"
    policy = "/runs/train/checkpoints/" + checkpoints[-1].name
    eval_env = {**stack.env, "SWIMM_EVAL_CHECKPOINT": policy, "SWIMM_EVAL_EPISODES": "1", "SWIMM_EVAL_STEPS": "200"}
    evaluation = ComposeProject(eval_env, stack.name, stack.folder)
    evaluation("--profile", "eval", "run", "--rm", "--no-deps", "eval", timeout_s=600)
    summary = json.loads((stack.folder / "runs" / "eval" / "summary.json").read_text())
    assert summary, f"eval wrote an empty report:\n{stack.logs()}"
