"""Over Zenoh a run checks that every live encoder runs the CMVAE its models will record (real processes)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

ROBUST = "encoder_service/models/cmvae_robust.pt"


def swimm(command: str, endpoint: str, namespace: str, *flags: str) -> subprocess.CompletedProcess:
    """A real `swimm <command>` on the cmvae observation against the test's router and namespace."""
    argv = [sys.executable, "-m", "swimm", command, "--obs", "cmvae", "--connect", endpoint,
            "--namespace", namespace, "--no-progress-bar", *flags]  # fmt: skip
    return subprocess.run(argv, capture_output=True, text=True, timeout=240)


def learn(endpoint: str, namespace: str, run_dir, *flags: str) -> subprocess.CompletedProcess:
    return swimm("learn", endpoint, namespace, "--backend", "zenoh", "--algo", "sac", "--steps", "64",
                 "--no-eval-enabled", "--run-dir", str(run_dir), *flags)  # fmt: skip


def test_a_run_on_another_cmvae_than_the_live_encoders_is_refused_naming_both(
    group, zenoh_router: str, namespace: str, tmp_path
) -> None:
    start_sim(group, zenoh_router, namespace)
    group.start("encoder", "encoder", "--connect", zenoh_router, "--namespace", namespace, "--checkpoint", ROBUST)
    refused = learn(zenoh_router, namespace, tmp_path / "refused")  # the default CMVAE, not the encoder's
    assert refused.returncode != 0
    assert "reads encoder" in refused.stderr and ROBUST in refused.stderr, refused.stderr
    assert not (tmp_path / "refused" / "final_model.zip").exists()
    accepted = learn(zenoh_router, namespace, tmp_path / "accepted", "--encoder-checkpoint", ROBUST)
    assert accepted.returncode == 0, accepted.stderr[-2000:]
    assert "every live encoder" in accepted.stderr


def evaluate(endpoint: str, namespace: str, out, *flags: str) -> subprocess.CompletedProcess:
    return swimm("eval", endpoint, namespace, "--algo", "scripted-camera", "--episodes", "1", "--steps", "20",
                 "--out", str(out), "--no-figures", *flags)  # fmt: skip


def test_an_evaluation_on_another_cmvae_than_the_live_encoders_is_refused(
    group, zenoh_router: str, namespace: str, tmp_path
) -> None:
    start_sim(group, zenoh_router, namespace)
    group.start("encoder", "encoder", "--connect", zenoh_router, "--namespace", namespace, "--checkpoint", ROBUST)
    refused = evaluate(zenoh_router, namespace, tmp_path / "refused")
    assert refused.returncode != 0
    assert "this evaluation" in refused.stderr and ROBUST in refused.stderr, refused.stderr
    accepted = evaluate(zenoh_router, namespace, tmp_path / "accepted", "--encoder-checkpoint", ROBUST)
    assert accepted.returncode == 0, accepted.stderr[-2000:]
    assert (tmp_path / "accepted" / "summary.json").is_file()
