"""Groups of envs stepped as one message each way (learner_service/link.py) over real processes.

A ProxyVecEnv whose envs travel in groups must play exactly the episodes that a DummyVecEnv of in-process
TrackingEnvs plays from the same seeds, whatever the grouping: rewards, dones, endings and (state observations)
every observation bit for bit. Under the torch engine latents are compared to float32 rounding only: the encoder
encodes a group in one forward pass, and a batched convolution sums in another order than one frame at a time
(differences of 1e-8); the onnx engine is batch-invariant, so there latents too are equal bit for bit.

Killing the encoder that serves the groups while they are in flight must move them to another encoder without
losing or repeating a step: the run stays equal to the in-process one.
"""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pytest
import torch
from stable_baselines3.common.vec_env import DummyVecEnv

from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint
from learner_service.inprocess_env import TrackingEnv
from learner_service.link import StepRefused
from learner_service.proxy_env import ProxySettings, ProxyVecEnv
from learner_service.task import TaskSettings
from services.low_latency import largest_low_latency_group
from services.messages import BatchMsg, LatentMsg, batch_messages
from sim_service.settings import WorldSettings
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

BASE_SEED = 103
ENVS = 5
STEPS = 160
TASK = TaskSettings(obs="cmvae", max_steps=60)  # short episodes: auto-resets inside the run
LATENT_ATOL = 1e-6


@pytest.fixture
def checkpoint(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "tiny-cmvae.pt"
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    return path


def actions() -> np.ndarray:
    rng = np.random.default_rng(5)
    return np.clip(rng.normal([0.3, 0.0], [0.4, 0.5], (STEPS, ENVS, 2)), -1, 1).astype(np.float32)


def record(vec_env, on_step=None) -> list[tuple]:
    rows = [(vec_env.reset(),)]
    for step, action in enumerate(actions()):
        obs, rewards, dones, infos = vec_env.step(action)
        terminal = [info.get("terminal_observation") for info in infos]
        rows.append((obs, rewards, dones, terminal, [info["cause"] for info in infos]))
        if on_step is not None:
            on_step(step)
    vec_env.close()
    return rows


def in_process(task: TaskSettings, checkpoint, engine: str = "torch") -> list[tuple]:
    encoder = LatentEncoder(checkpoint, engine=engine) if task.obs == "cmvae" else None
    factories = [lambda i=i: TrackingEnv(task, base_seed=BASE_SEED + i, encoder=encoder) for i in range(ENVS)]
    return record(DummyVecEnv(factories))


def assert_same(remote: list[tuple], local: list[tuple], atol: float = 0.0) -> None:
    """Rewards, dones and causes equal; observations (and terminal ones) equal within ``atol``."""
    assert len(remote) == len(local)
    for row, (got, want) in enumerate(zip(remote, local, strict=True)):
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=atol, err_msg=f"row {row}: observations differ")
        if row == 0:
            continue
        np.testing.assert_array_equal(got[1], want[1], err_msg=f"row {row}: rewards differ")
        np.testing.assert_array_equal(got[2], want[2], err_msg=f"row {row}: dones differ")
        assert got[4] == want[4], f"row {row}: causes differ"
        for a, b in zip(got[3], want[3], strict=True):
            assert (a is None) == (b is None), f"row {row}: terminal observations differ"
            if a is not None:
                np.testing.assert_allclose(a, b, rtol=0, atol=atol, err_msg=f"row {row}: terminal observations")
    assert sum(int(np.sum(row[2])) for row in local[1:]) >= ENVS, "the run should end episodes and auto-reset"


def start_pipeline(group, namespace, checkpoint, encoders: list[str], engine: str = "torch") -> tuple[str, dict]:
    """The router's endpoint and the encoders' processes by id."""
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", str(ENVS), "--eval-envs", "0")
    started = {
        ident: group.start(ident, "encoder", "--connect", endpoint, "--namespace", namespace, "--checkpoint",
                           str(checkpoint), "--ident", ident, "--engine", engine).process
        for ident in encoders
    }  # fmt: skip
    return endpoint, started


@pytest.mark.parametrize(
    ("obs", "group_size", "engine"),
    [("state", 2, "torch"), ("cmvae", 2, "torch"), ("cmvae", ENVS, "torch"), ("cmvae", 2, "onnx")],
)
def test_grouped_steps_equal_the_in_process_vec_env(
    group, namespace, zenoh_settings, checkpoint, obs, group_size, engine
) -> None:
    task = TaskSettings(obs=obs, max_steps=TASK.max_steps)
    endpoint, _ = start_pipeline(group, namespace, checkpoint, ["enc-a"] if obs == "cmvae" else [], engine)
    proxy = ProxySettings(zenoh=zenoh_settings(endpoint), envs=tuple(map(str, range(ENVS))), group_size=group_size)
    remote_env = ProxyVecEnv(task, proxy, base_seed=BASE_SEED)
    assert [len(link.envs) for link in remote_env.links] == ([2, 2, 1] if group_size == 2 else [ENVS])
    exact = obs == "state" or engine == "onnx"
    assert_same(record(remote_env), in_process(task, checkpoint, engine), atol=0.0 if exact else LATENT_ATOL)


def test_killing_the_groups_encoder_mid_run_loses_or_repeats_no_step(
    group, namespace, zenoh_settings, checkpoint
) -> None:
    endpoint, encoders = start_pipeline(group, namespace, checkpoint, ["enc-a", "enc-b"])
    proxy = ProxySettings(zenoh=zenoh_settings(endpoint), envs=tuple(map(str, range(ENVS))), group_size=2,
                          step_timeout_s=1.0)  # fmt: skip
    remote_env = ProxyVecEnv(TASK, proxy, base_seed=BASE_SEED)
    remote_env.envs[0].link.encoders.wait_for(2, timeout_s=30)
    served_by: list[str] = []  # the encoder of every group step's reply (not a reset's), in order
    groups = remote_env.links
    names = {link.group for link in groups}

    def tap_reply(sample) -> None:
        reply = BatchMsg.decode(sample.payload.to_bytes())
        if reply.group in names:
            served_by.append(reply.sender)

    tap = remote_env.session.declare_subscriber(f"{namespace}/train/*/latent", tap_reply)
    killed: dict[str, object] = {}

    def kill_the_busiest_encoder(step: int) -> None:
        if step != STEPS // 2:
            return
        victim = max(encoders, key=served_by.count)
        os.kill(encoders[victim].pid, signal.SIGSTOP)  # frozen first, so it dies holding a group in flight
        threading.Timer(0.2, os.kill, (encoders[victim].pid, signal.SIGKILL)).start()
        killed.update(victim=victim, replies_before=len(served_by))

    remote = record(remote_env, on_step=kill_the_busiest_encoder)
    tap.undeclare()
    assert_same(remote, in_process(TASK, checkpoint), atol=LATENT_ATOL)
    assert sum(g.retries for g in groups) >= 1, "the kill should have caught a group in flight"
    before_kill = served_by[: killed["replies_before"]]
    assert set(before_kill) == set(encoders), "the learner's three groups should spread over both encoders"
    fewer, more = sorted(map(before_kill.count, encoders))  # one group's replies and two groups' (retries add some)
    assert fewer >= STEPS // 2 and more >= 2 * (STEPS // 2)
    assert killed["victim"] not in served_by[killed["replies_before"] + 3 :]


def test_ungrouped_envs_spread_evenly_over_the_encoders_and_play_the_in_process_episodes(
    group, namespace, zenoh_settings, checkpoint
) -> None:
    """Without groups each env's frames go to one encoder, chosen over the learner's envs with bounded load.

    Named so that plain rendezvous hashing would send four of the five envs to enc-a (and one to enc-e)."""
    endpoint, encoders = start_pipeline(group, namespace, checkpoint, ["enc-a", "enc-e"])
    proxy = ProxySettings(zenoh=zenoh_settings(endpoint), envs=tuple(map(str, range(ENVS))), group_size=0)
    remote_env = ProxyVecEnv(TASK, proxy, base_seed=BASE_SEED)
    assert [link.envs for link in remote_env.links] == [(str(env),) for env in range(ENVS)]  # each its own group
    for env in remote_env.envs:  # each env's roster sees both, or its first frames would go to the one it saw
        env.link.encoders.wait_for(2, timeout_s=30)
    encoder_of: dict[str, set[str]] = {}  # env -> the encoders that sent its latents

    def tap_latent(sample) -> None:
        for env, latent in batch_messages(sample.payload.to_bytes(), LatentMsg.from_item):
            encoder_of.setdefault(env, set()).add(latent.encoder)

    tap = remote_env.session.declare_subscriber(f"{namespace}/train/*/latent", tap_latent)
    remote = record(remote_env)
    tap.undeclare()
    assert_same(remote, in_process(TASK, checkpoint), atol=LATENT_ATOL)
    assert sorted(encoder_of) == sorted(map(str, range(ENVS)))
    assert all(len(served) == 1 for served in encoder_of.values()), encoder_of  # no encoder left, none moved
    loads = [sum(served == {ident} for served in encoder_of.values()) for ident in encoders]
    assert sorted(loads) == [ENVS // 2, ENVS - ENVS // 2], encoder_of


def test_a_group_step_the_sim_cannot_take_is_refused_naming_the_env(group, connect_client, namespace) -> None:
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", "1", "--eval-envs", "0")
    client = connect_client(endpoint)
    link = client.link(envs=["0", "7"], group="g", step_timeout_s=1.0)
    link.claim(timeout_s=30)
    link.send_reset(1, seed=5)
    link.wait()
    link.ep[1] = 1  # as if it had been reset: the sim must refuse it for what it is, an env it does not serve
    link.send([(0.0, 0.0, 0.5, 0.0)] * 2)
    with pytest.raises(StepRefused, match="train/7.*not served"):
        link.wait()
    link.close()


def test_a_low_latency_sim_answers_the_largest_group_one_message_holds_and_refuses_a_larger_one(
    group, connect_client, namespace
) -> None:
    """That transport cannot fragment: a larger group's reply would be lost, so the sim says why, without stepping."""
    endpoint = group.start_router(flags=("--low-latency",))
    largest = largest_low_latency_group(WorldSettings().image_size)
    start_sim(group, endpoint, namespace, "--low-latency", "--train-envs", str(largest + 1), "--eval-envs", "0")
    client = connect_client(endpoint, low_latency=True)
    client.roster("sim").wait_for(1, timeout_s=60)
    envs = [str(env) for env in range(largest + 1)]
    too_large = client.link(envs=envs, group="too-large", step_timeout_s=1.0, max_retries=2)
    for index in range(len(envs)):
        too_large.claim(timeout_s=30, index=index)
        too_large.send_reset(1, seed=5 + index, index=index)
        too_large.wait()
    fits = client.link(envs=envs[:largest], group="fits", step_timeout_s=1.0, max_retries=2)
    fits.ep = [1] * largest  # the same holder's envs, reset above
    fits.send([(0.0, 0.0, 0.5, 0.0)] * largest)
    replies = fits.wait()
    assert fits.seq == [1] * largest
    assert all(reply.image.shape == (WorldSettings().image_size,) * 2 + (3,) for reply in replies)
    fits.close()
    too_large.seq = [1] * largest + [0]  # where ``fits`` left them
    too_large.send([(0.0, 0.0, 0.5, 0.0)] * len(envs))
    with pytest.raises(StepRefused, match=f"--group-size {largest} or less"):
        too_large.wait()
    # Refused before stepping: the last env is still at seq 0, so a step 2 is out of order.
    last = client.link(env=envs[-1], step_timeout_s=1.0, max_retries=2)
    last.ep, last.seq = [1], [1]
    last.send([(0.0, 0.0, 0.5, 0.0)])
    with pytest.raises(StepRefused, match="seq 2 out of order"):
        last.wait()
