"""The same seeds and actions give the same run over Zenoh (router, sim, encoder processes) as in one process.

Each run goes through several episodes (early endings and time-limit truncations both) with a fixed action
sequence, and records everything the learner sees: observations, rewards, terminated/truncated and the
termination cause. In cmvae mode the latent comes from a `swimm encoder` process on one side and from a
LatentEncoder on the same checkpoint on the other, so the whole step path action -> sim -> encoder -> latent
is compared bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from encoder_service import POD_DETECTOR
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint
from encoder_service.pod_encoder import PodEncoder
from learner_service.inprocess_env import TrackingEnv, task_world
from learner_service.proxy_env import ProxyEnv, ProxySettings
from learner_service.task import TaskSettings
from sim_service.settings import DolphinSettings, WorldSettings
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

BASE_SEED = 101
STEPS = 300
MAX_STEPS = 100  # short time limit, so the fixed actions meet truncations as well as early terminations


def fixed_actions(task: str = "planar") -> np.ndarray:
    """Gentle noise, a hard spin that loses the dolphin, then full ahead: early endings and a time-limit truncation.

    The 3d task's heave (between surge and yaw) is gentle noise with a full climb, drawn after the planar actions.
    """
    rng = np.random.default_rng(11)
    actions = np.clip(rng.normal([0.2, 0.0], [0.3, 0.3], (STEPS, 2)), -1, 1)
    actions[60:120, 1] = 1.0
    actions[200:260] = (1.0, 0.0)
    if task == "3d":
        heave = np.clip(rng.normal(0.0, 0.3, STEPS), -1, 1)
        heave[120:200] = 1.0
        actions = np.insert(actions, 1, heave, axis=1)
    return actions.astype(np.float32)


def record_run(env) -> list[tuple]:
    """(obs, reward, terminated, truncated, cause, ep) per step, resetting after each episode ends."""
    obs, info = env.reset()
    rows: list[tuple] = [(obs, 0.0, False, False, info["cause"], info["ep"])]
    for action in fixed_actions(env.task.settings.task):
        obs, reward, terminated, truncated, info = env.step(action)
        rows.append((obs, reward, terminated, truncated, info["cause"], info["ep"]))
        if terminated or truncated:
            obs, info = env.reset()
            rows.append((obs, 0.0, False, False, info["cause"], info["ep"]))
    env.close()
    return rows


def assert_same_runs(remote: list[tuple], local: list[tuple]) -> None:
    assert len(remote) == len(local)
    for step, (got, want) in enumerate(zip(remote, local, strict=True)):
        np.testing.assert_array_equal(got[0], want[0], err_msg=f"observation differs at row {step}")
        assert got[1:] == want[1:], f"row {step}: reward/terminated/truncated/cause/ep differ"
    assert any(row[2] and row[4] for row in local), "the fixed actions should end an episode early, with its cause"
    assert any(row[3] and not row[2] for row in local), "the fixed actions should reach the time limit"


def test_state_mode_over_zenoh_equals_in_process(group, namespace, zenoh_settings) -> None:
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--eval-envs", "0")
    task = TaskSettings(obs="state", max_steps=MAX_STEPS)
    remote = record_run(ProxyEnv(task, ProxySettings(zenoh=zenoh_settings(endpoint)), base_seed=BASE_SEED))
    local = record_run(TrackingEnv(task, base_seed=BASE_SEED))
    assert_same_runs(remote, local)


def test_3d_task_over_zenoh_equals_in_process(group, namespace, zenoh_settings) -> None:
    """A sim started with the 3d dolphin serves the 3d task as the in-process env's own 3d world does."""
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--eval-envs", "0", "--dolphin-motion", "3d")
    task = TaskSettings(obs="state", task="3d", max_steps=MAX_STEPS)
    remote = record_run(ProxyEnv(task, ProxySettings(zenoh=zenoh_settings(endpoint)), base_seed=BASE_SEED))
    local = record_run(TrackingEnv(task, base_seed=BASE_SEED))
    assert_same_runs(remote, local)
    target_z = np.array([row[0][8] for row in local])  # the state observation's target z
    assert np.ptp(target_z) > 0.1  # the dolphin changed depth: the 3d motion ran on both sides


def test_cmvae_mode_over_zenoh_equals_in_process(group, namespace, zenoh_settings, tmp_path) -> None:
    torch.manual_seed(0)
    checkpoint = tmp_path / "tiny-cmvae.pt"
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), checkpoint)
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--eval-envs", "0")
    # One torch thread on both sides: the same kernels, so the same bits (this process's thread count is whatever
    # earlier tests left it at, and a convolution split over another number of threads differs in the last bits).
    group.start("encoder", "encoder", "--connect", endpoint, "--namespace", namespace, "--checkpoint", str(checkpoint),
                "--threads", "1")  # fmt: skip
    task = TaskSettings(obs="cmvae", max_steps=MAX_STEPS)
    remote = record_run(ProxyEnv(task, ProxySettings(zenoh=zenoh_settings(endpoint)), base_seed=BASE_SEED))
    threads = torch.get_num_threads()
    try:
        local = record_run(TrackingEnv(task, base_seed=BASE_SEED, encoder=LatentEncoder(checkpoint, threads=1)))
    finally:
        torch.set_num_threads(threads)
    assert_same_runs(remote, local)
    assert np.abs(np.array([row[0][:10] for row in local])).max() > 0  # real latents, not zeros


def test_pod_detector_over_zenoh_equals_in_process(group, namespace, zenoh_settings) -> None:
    """The pod tracker's state travels with each step (the encoder keeps none), so a `swimm encoder` on the pod
    detector gives the latents the detector and tracker give in process, over a pod of 4, episode after episode."""
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--eval-envs", "0", "--dolphin-pod-size", "4")
    group.start("encoder", "encoder", "--connect", endpoint, "--namespace", namespace, "--checkpoint",
                str(POD_DETECTOR), "--threads", "1")  # fmt: skip
    task = TaskSettings(obs="cmvae", max_steps=MAX_STEPS)
    remote = record_run(ProxyEnv(task, ProxySettings(zenoh=zenoh_settings(endpoint)), base_seed=BASE_SEED))
    pod = WorldSettings(dolphin=DolphinSettings(pod_size=4))
    threads = torch.get_num_threads()
    try:
        world = task_world(task, base=pod)
        local = record_run(TrackingEnv(task, world, base_seed=BASE_SEED, encoder=PodEncoder(POD_DETECTOR, threads=1)))
    finally:
        torch.set_num_threads(threads)
    assert_same_runs(remote, local)
    distances = np.array([row[0][0] for row in local])
    assert np.unique(distances).size > 10  # the target read afresh frame after frame, not the unseen default
