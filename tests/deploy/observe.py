"""The deployment tests' shared parts: a stack's settings and mounted folders, and what they watch from outside
through the router's published port (every latent)."""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from pathlib import Path

import pytest
import torch

from encoder_service.model import CMVAE, make_checkpoint
from services.keys import Keys
from services.messages import LatentMsg, batch_messages
from sim_service.settings import WorldSettings
from tests.deploy.docker_stack import SIM_TAG, TORCH_TAG


def stack_settings(folder: Path, port: int, label: str, envs: int) -> dict[str, str]:
    """The SWIMM_* variables of a test stack of ``envs`` train envs whose router the host reaches on ``port``, with
    ``folder``'s models/ (an untrained CMVAE: the tests are about the pipeline, not the latents' meaning) and runs/."""
    (folder / "models").mkdir()
    (folder / "runs").mkdir()
    torch.manual_seed(0)
    torch.save(
        make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), folder / "models" / "cmvae.pt"
    )
    return {
        "SWIMM_SIM_IMAGE": SIM_TAG,
        "SWIMM_TORCH_IMAGE": TORCH_TAG,
        "SWIMM_ROUTER_PORT": str(port),
        "SWIMM_NAMESPACE": f"swimm/{label}-{time.time_ns() % 10**8}",
        "SWIMM_MODELS": str(folder / "models"),
        "SWIMM_RUNS": str(folder / "runs"),
        "SWIMM_ENCODER_CHECKPOINT": "/models/cmvae.pt",
        "SWIMM_ENVS": str(envs),
        "SWIMM_STEPS": "100000",
        # Small and frequent: updates and checkpoints show up within the test's minutes on a CPU.
        "SWIMM_HYPERPARAMS": "{learning_starts: 100, train_freq: [16, step], gradient_steps: 8, batch_size: 64}",
    }


class LatentLog:
    """Every latent on ``<ns>/train/*/latent``, as seen by an outside observer."""

    def __init__(self, session, keys: Keys) -> None:
        self.rows: list[tuple[str, int, int, float, str]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(f"{keys.namespace}/train/*/latent", self._on_latent)

    def _on_latent(self, sample) -> None:
        with self._lock:
            for env, msg in batch_messages(sample.payload.to_bytes(), LatentMsg.from_item):
                self.rows.append((env, msg.ep, msg.seq, msg.telemetry.sim_time, msg.encoder))

    def snapshot(self) -> list[tuple[str, int, int, float, str]]:
        with self._lock:
            return list(self.rows)

    def steps(self) -> int:
        return len({row[:3] for row in self.snapshot()})

    def close(self) -> None:
        self._sub.undeclare()


def wait_until(condition, timeout_s: float, what: str, stack) -> None:
    """Poll ``condition`` each second; past ``timeout_s`` fail naming ``what``, with the ``stack.logs()``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}\n{stack.logs()}")
        time.sleep(1.0)


def check_no_step_lost_or_repeated(rows: list[tuple[str, int, int, float, str]], envs: int) -> None:
    """Each (env, ep) seen: seqs 0..n without a gap, and the sim's clock at seq * dt (applied once each).

    A latent may arrive twice (a re-sent step is answered from the sim's cache and encoded again); both
    copies then carry the same clock. Episodes already running when the observer joined are skipped.
    """
    dt = WorldSettings().physics_dt
    clocks: dict[tuple[str, int], dict[int, set[int]]] = defaultdict(lambda: defaultdict(set))
    for env, ep, seq, sim_time, _ in rows:
        clocks[(env, ep)][seq].add(round(sim_time / dt))
    whole = [key for key, seqs in clocks.items() if 0 in seqs]
    assert len(whole) >= envs
    for key in whole:
        seqs = clocks[key]
        assert sorted(seqs) == list(range(max(seqs) + 1)), f"{key}: a step is missing"
        assert all(ticks == {seq} for seq, ticks in seqs.items()), f"{key}: a step was applied twice"
