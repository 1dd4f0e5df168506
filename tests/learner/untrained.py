"""An untrained camera-only SAC saved for the export and pilot tests, stamped with the encoder it observes."""

from __future__ import annotations

from pathlib import Path

from encoder_service.inference import open_encoder
from learner_service.envs import make_vec_env
from learner_service.identity import policy_identity, stamp
from learner_service.registry import make_model
from learner_service.task import TaskSettings


def untrained_sac(encoder: Path, task: str, path: Path) -> None:
    """Save an untrained camera-only SAC of ``task`` on ``encoder`` (a CMVAE or a pod detector) at ``path``."""
    settings = TaskSettings(obs="cmvae", task=task, max_steps=20)
    env = make_vec_env("inprocess", settings, n_envs=1, base_seed=1, encoder=open_encoder(encoder))
    try:
        model = make_model("sac", env, seed=1, overrides={"device": "cpu", "buffer_size": 100})
        stamp(model, policy_identity(encoder, "cmvae", "swimm2", task))
        model.save(path)
    finally:
        env.close()
