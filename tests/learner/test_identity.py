"""A policy knows its encoder: saved with the model, taken by default, and a mismatched pair refused by name.

Real SB3 checkpoints (the shipped ones, and a model trained here), real CMVAE files, the real commands' entry points.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from dataclasses import replace
from pathlib import Path

import pytest

from eval_service.engine import EvaluationSettings, with_policy_encoder
from learner_service.command import Training
from learner_service.export import ExportSettings
from learner_service.export import run as export
from learner_service.identity import encoder_for, read_identity
from learner_service.learn_settings import EvalSettings, LearnCommandSettings
from services.results import REPO_ROOT, file_sha256

MODELS = REPO_ROOT / "learner_service" / "models"
ENCODERS = REPO_ROOT / "encoder_service" / "models"
SHIPPED_PAIRS = {"sac_cmvae.zip": "cmvae.pt", "sac_cmvae_robust.zip": "cmvae_robust.pt",
                 "sac_cmvae_latency.zip": "cmvae_mixture.pt", "sac_cmvae_3d.zip": "cmvae_vertical.pt",
                 "sac_cmvae_3d_robust.zip": "cmvae_vertical_robust.pt",
                 "sac_pod_detector.zip": "pod_detector.pt", "sac_cmvae_wide.zip": "cmvae_wide.pt",
                 "sac_cmvae_fans.zip": "cmvae_fans.pt"}  # fmt: skip


@pytest.mark.parametrize(("policy", "encoder"), SHIPPED_PAIRS.items())
def test_each_shipped_policy_records_the_encoder_it_was_trained_on(policy, encoder) -> None:
    identity = read_identity(MODELS / policy)
    assert identity["encoder"]["sha256"] == file_sha256(ENCODERS / encoder)
    assert encoder_for(MODELS / policy, None) == ENCODERS / encoder


def test_a_mismatched_pair_is_refused_naming_both_files() -> None:
    with pytest.raises(ValueError, match=r"sac_cmvae_robust.zip was trained on encoder .*cmvae_robust.pt.*cmvae.pt"):
        encoder_for(MODELS / "sac_cmvae_robust.zip", ENCODERS / "cmvae.pt")
    assert encoder_for(MODELS / "sac_cmvae_robust.zip", ENCODERS / "cmvae_robust.pt") == ENCODERS / "cmvae_robust.pt"


def test_eval_takes_the_policys_encoder_and_refuses_another(tmp_path) -> None:
    given = EvaluationSettings(checkpoint=[str(MODELS / "sac_cmvae_latency.zip")], algo=["sac", "scripted-camera"])
    assert Path(with_policy_encoder(given).encoder_checkpoint) == ENCODERS / "cmvae_mixture.pt"
    with pytest.raises(ValueError, match="cmvae_mixture.pt"):
        with_policy_encoder(replace(given, encoder_checkpoint=str(ENCODERS / "cmvae.pt")))
    both = replace(given, checkpoint=[str(MODELS / "sac_cmvae_latency.zip"), str(MODELS / "sac_cmvae.zip")],
                   algo=["sac"])  # fmt: skip
    with pytest.raises(ValueError, match="trained on different encoders"):
        with_policy_encoder(both)


def test_export_refuses_a_mismatched_pair_before_writing(tmp_path) -> None:
    out = tmp_path / "policy.onnx"
    with pytest.raises(ValueError, match="sac_cmvae_robust.zip was trained on encoder"):
        export(ExportSettings(checkpoint=str(MODELS / "sac_cmvae_robust.zip"),
                              encoder_checkpoint=str(ENCODERS / "cmvae.pt"), out=str(out)))  # fmt: skip
    assert not out.exists() and not list(tmp_path.iterdir())


def test_a_file_that_is_no_policy_is_refused_with_its_path(tmp_path) -> None:
    text = tmp_path / "notes.zip"
    text.write_text("not a zip")
    with pytest.raises(ValueError, match=f"{text} is not a policy checkpoint"):
        read_identity(text)
    other = tmp_path / "other.zip"
    with zipfile.ZipFile(other, "w") as archive:
        archive.writestr("readme.txt", "a zip, but no model")
    with pytest.raises(ValueError, match=f"{other} is not a policy checkpoint"):
        encoder_for(other, None)


def test_a_trained_model_records_its_encoder_and_a_resume_on_another_is_refused(tmp_path) -> None:
    """A tiny in-process run saves its final model with the identity; resuming it on another CMVAE fails early."""
    encoder = tmp_path / "my_cmvae.pt"
    shutil.copy(ENCODERS / "cmvae_robust.pt", encoder)
    settings = LearnCommandSettings(algo="sac", obs="cmvae", backend="inprocess", steps=40, seed=5, max_steps=40,
                                    encoder_checkpoint=str(encoder), run_dir=str(tmp_path / "run"),
                                    hyperparams="{learning_starts: 10, batch_size: 8, gradient_steps: 1}",
                                    checkpoint_every=0, eval=EvalSettings(enabled=False),
                                    progress_bar=False)  # fmt: skip
    Training(settings).run()
    final = tmp_path / "run" / "final_model.zip"
    assert read_identity(final)["encoder"]["sha256"] == file_sha256(encoder)
    resumed = replace(settings, resume=str(final), encoder_checkpoint=str(ENCODERS / "cmvae.pt"),
                      run_dir=str(tmp_path / "resumed"))  # fmt: skip
    with pytest.raises(ValueError, match="final_model.zip was trained on encoder"):
        Training(resumed).run()


def test_a_policy_runs_only_on_the_task_it_was_trained_on(tmp_path) -> None:
    """A 3d policy is refused on the planar task by resume and by evaluation, and a policy saved before the task was
    recorded (the shipped ones) reads as planar and is refused on the 3d task; each error names both tasks."""
    from learner_service.registry import load_policy

    settings = LearnCommandSettings(algo="sac", obs="state", task="3d", backend="inprocess", steps=40, seed=5,
                                    max_steps=40, run_dir=str(tmp_path / "run"),
                                    hyperparams="{learning_starts: 10, batch_size: 8, gradient_steps: 1}",
                                    checkpoint_every=0, eval=EvalSettings(enabled=False),
                                    progress_bar=False)  # fmt: skip
    Training(settings).run()
    final = tmp_path / "run" / "final_model.zip"
    assert load_policy("sac", final, task="3d", device="cpu") is not None
    refusal = "final_model.zip was trained on the 3d task, but this is the planar task"
    with pytest.raises(ValueError, match=refusal):
        load_policy("sac", final, task="planar")
    resumed = replace(settings, task="planar", resume=str(final), run_dir=str(tmp_path / "resumed"))
    with pytest.raises(ValueError, match=refusal):
        Training(resumed).run()
    with pytest.raises(ValueError, match="sac_cmvae.zip was trained on the planar task, but this is the 3d task"):
        load_policy("sac", MODELS / "sac_cmvae.zip", task="3d")


def test_eval_refuses_a_zip_that_is_no_model_with_its_path(tmp_path) -> None:
    """The first-hour trap: a zip that is not a model used to fail as 'No data found in the saved file'."""
    from learner_service.registry import load_policy

    other = tmp_path / "photos.zip"
    with zipfile.ZipFile(other, "w") as archive:
        archive.writestr("a.txt", "holiday")
    with pytest.raises(ValueError, match=f"{other} is not a policy checkpoint: expected a stable-baselines3 model"):
        load_policy("sac", other)


def test_reading_a_policys_encoder_needs_no_zenoh() -> None:
    """export and pilot only read a checkpoint; the Zenoh half of the check lives in learner_service.live_encoders."""
    probe = "import sys, learner_service.identity; print('zenoh' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO_ROOT, check=True)
    assert result.stdout.strip() == "False"


def test_a_policy_saved_before_identities_is_warned_of_once(tmp_path, caplog) -> None:
    """A command's check and its run both ask for the encoder: the user reads the warning once."""
    legacy = tmp_path / "legacy.zip"
    with zipfile.ZipFile(legacy, "w") as archive:
        archive.writestr("data", "{}")
    with caplog.at_level("WARNING", logger="learner_service.identity"):
        assert encoder_for(legacy, None) is None
        assert encoder_for(legacy, None) is None
        assert encoder_for(legacy, ENCODERS / "cmvae.pt") == ENCODERS / "cmvae.pt"
    warned = [r.getMessage() for r in caplog.records if "records no encoder" in r.getMessage()]
    said = f"{legacy} records no encoder (saved before policies carried one); using"
    assert warned == [f"{said} the default CMVAE", f"{said} {ENCODERS / 'cmvae.pt'}"]
