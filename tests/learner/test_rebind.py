"""`swimm rebind`: a policy copied to fly on a fine-tune of its CMVAE, its identity saying both.

Real shipped policies and CMVAE files, the real command's entry point.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from stable_baselines3 import SAC

from encoder_service.model import CMVAE, make_checkpoint
from learner_service.identity import TRAINED_ON_KEY, encoder_for, policy_identity, read_identity, stamp
from learner_service.registry import load_policy
from services.results import REPO_ROOT, file_sha256
from swimm.cli import main as swimm

MODELS = REPO_ROOT / "learner_service" / "models"
ENCODERS = REPO_ROOT / "encoder_service" / "models"
POLICY, TRAINED_ON, FINE_TUNE = MODELS / "sac_cmvae_wide.zip", ENCODERS / "cmvae_wide.pt", ENCODERS / "cmvae_fans.pt"


def _actions(checkpoint) -> np.ndarray:
    policy = load_policy("sac", checkpoint, device="cpu")
    obs = np.random.default_rng(0).uniform(-1, 1, (6, *policy.model.observation_space.shape)).astype(np.float32)
    return policy.act(obs, {})


def test_a_rebound_copy_acts_as_the_policy_and_flies_only_on_the_new_cmvae(tmp_path) -> None:
    out = tmp_path / "copy.zip"
    argv = ["rebind", "--checkpoint", str(POLICY), "--encoder-checkpoint", str(FINE_TUNE), "--out", str(out)]
    assert swimm(argv) == 0

    np.testing.assert_array_equal(_actions(out), _actions(POLICY))
    identity = read_identity(out)
    assert identity["encoder"]["sha256"] == file_sha256(FINE_TUNE)
    assert identity[TRAINED_ON_KEY]["sha256"] == file_sha256(TRAINED_ON)
    assert identity["task"] == read_identity(POLICY)["task"]
    assert encoder_for(out, None) == FINE_TUNE
    with pytest.raises(ValueError, match=r"copy.zip was trained on encoder .*cmvae_fans.pt.*cmvae_wide.pt"):
        encoder_for(out, TRAINED_ON)

    # a copy of the copy still names the CMVAE the weights trained on
    again = tmp_path / "again.zip"
    rebind_back = ["rebind", "--checkpoint", str(out), "--encoder-checkpoint", str(ENCODERS / "cmvae_general.pt"),
                   "--out", str(again)]  # fmt: skip
    assert swimm(rebind_back) == 0
    assert read_identity(again)[TRAINED_ON_KEY]["sha256"] == file_sha256(TRAINED_ON)


def _refusal(tmp_path, capfd, **flags) -> str:
    given = {"checkpoint": str(POLICY), "encoder_checkpoint": str(FINE_TUNE), "out": str(tmp_path / "copy.zip")}
    given.update(flags)
    argv = ["rebind"] + [part for key, value in given.items() if value is not None
                         for part in (f"--{key.replace('_', '-')}", value)]  # fmt: skip
    assert swimm(argv) == 2
    return capfd.readouterr().err


def test_what_would_make_a_wrong_copy_is_refused_by_name_and_nothing_is_written(tmp_path, capfd) -> None:
    other_size = tmp_path / "cmvae_8.pt"
    torch.save(make_checkpoint(CMVAE(n_z=8), beta=8.0, epoch=1, val_loss=0.1, metrics={}), other_size)
    kept = tmp_path / "kept.zip"
    kept.write_bytes(b"already here")
    state_policy = tmp_path / "state.zip"
    model = SAC.load(MODELS / "sac_cmvae.zip", device="cpu")
    stamp(model, policy_identity("", "state", "swimm2"))  # as a policy on the true state records itself
    model.save(state_policy)
    mine = tmp_path / "mine.zip"
    mine.write_bytes(POLICY.read_bytes())

    assert "--out is required" in _refusal(tmp_path, capfd, out="")
    assert "is the CMVAE the policy already records" in _refusal(tmp_path, capfd, encoder_checkpoint=str(TRAINED_ON))
    assert "cmvae_8.pt writes 8 latents, but encoder_service/models/cmvae_wide.pt" in _refusal(
        tmp_path, capfd, encoder_checkpoint=str(other_size)
    )
    assert "is not a swimm-cmvae checkpoint" in _refusal(
        tmp_path, capfd, encoder_checkpoint=str(MODELS / "sac_cmvae.zip")
    )
    assert "state.zip records no CMVAE" in _refusal(tmp_path, capfd, checkpoint=str(state_policy))
    assert "pod_detector.pt is a pod detector, not a CMVAE" in _refusal(
        tmp_path, capfd, checkpoint=str(MODELS / "sac_pod_detector.zip")
    )
    assert "must not replace the policy" in _refusal(tmp_path, capfd, checkpoint=str(mine), out=str(mine))
    assert "kept.zip exists: give --overwrite" in _refusal(tmp_path, capfd, out=str(kept))
    assert "unknown algorithm 'nope'" in _refusal(tmp_path, capfd, algo="nope")
    assert kept.read_bytes() == b"already here" and not (tmp_path / "copy.zip").exists()
