"""A policy knows its encoder: the CMVAE a policy was trained on travels inside its checkpoint.

A camera-only policy reads latents, and a latent means something only to the encoder that made it: the slow-loop
policy flies on `cmvae_mixture.pt` and fails on any other, silently. So a trained model carries
:data:`IDENTITY_KEY` (the encoder's path and content hash, and the task's name, observation and reward), saved by
stable-baselines3 with the model's other attributes, and every command that loads a policy takes that encoder by
default (:func:`encoder_for`) and refuses another by name. Likewise a policy acts in the task it was trained on
(the planar task's (surge, yaw) or the 3d task's (surge, heave, yaw)): another is refused (:func:`check_task`).
"""

from __future__ import annotations

import functools
import json
import logging
import zipfile
from pathlib import Path
from typing import Any

from services.results import REPO_ROOT, file_sha256

log = logging.getLogger(__name__)

#: The model attribute (and key of the zip's ``data`` JSON) that holds the identity.
IDENTITY_KEY = "swimm_identity"
#: The identity's key for the CMVAE a policy trained on, where it flies on another (`swimm rebind`, a fine-tune).
TRAINED_ON_KEY = "trained_on"
#: The task of a policy that records none: it was saved before the 3d task existed.
LEGACY_TASK = "planar"
#: Where a recorded encoder is looked for when its recorded path is not here (e.g. a run folder elsewhere).
SHIPPED_ENCODERS = REPO_ROOT / "encoder_service" / "models"


def policy_identity(encoder: str | Path, obs: str, reward: str, task: str = LEGACY_TASK) -> dict[str, Any]:
    """The identity a model trained on ``task`` with ``encoder``'s latents (or on ``obs`` without an encoder)
    carries."""
    identity: dict[str, Any] = {"task": {"name": task, "obs": obs, "reward": reward}}
    if obs == "cmvae":
        path = Path(encoder)
        identity["encoder"] = {"path": _shown(path), "sha256": file_sha256(path)}
    return identity


def stamp(model: Any, identity: dict[str, Any]) -> None:
    """Make every later ``model.save`` carry ``identity`` (SB3 saves JSON-able attributes and restores them)."""
    setattr(model, IDENTITY_KEY, identity)


def read_identity(checkpoint: str | Path) -> dict[str, Any] | None:
    """The identity saved in an SB3 checkpoint, None for one saved before identities existed.

    Read from the zip without loading the model, and a file that is no SB3 model is refused with its path.
    """
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"policy checkpoint {path} does not exist (train one with `swimm learn`)")
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, UnicodeDecodeError):
        raise ValueError(
            f"{path} is not a policy checkpoint: expected a stable-baselines3 model zip (as `swimm learn` saves, "
            f"e.g. best_model.zip) holding a 'data' entry"
        ) from None
    identity = data.get(IDENTITY_KEY)
    return identity if isinstance(identity, dict) else None


def policy_task(checkpoint: str | Path) -> str:
    """The task ``checkpoint`` was trained on: the one it records, else planar (:data:`LEGACY_TASK`)."""
    recorded = (read_identity(checkpoint) or {}).get("task", {})
    return recorded.get("name", LEGACY_TASK)


def check_task(checkpoint: str | Path, task: str) -> None:
    """Refuse to run ``checkpoint`` on ``task`` when it was trained on another, naming both."""
    trained = policy_task(checkpoint)
    if trained != task:
        raise ValueError(
            f"policy {checkpoint} was trained on the {trained} task, but this is the {task} task (their actions "
            f"differ): run it with --task {trained}, or train a policy on the {task} task"
        )


def encoder_for(checkpoint: str | Path, given: str | Path | None) -> Path | None:
    """The CMVAE to run ``checkpoint`` with: the one it records, found by hash; ``given`` must be that one.

    None when the policy records no encoder and none is given (the caller's default applies). A ``given`` encoder
    with another hash is refused naming both files.
    """
    identity = read_identity(checkpoint)
    recorded = (identity or {}).get("encoder")
    if recorded is None:
        if identity is None:
            _warn_no_encoder(str(checkpoint), str(given or "the default CMVAE"))
        return Path(given) if given else None
    if given:
        if file_sha256(given) != recorded["sha256"]:
            raise ValueError(
                f"policy {checkpoint} was trained on encoder {recorded['path']} (sha256 {recorded['sha256'][:12]}), "
                f"but the encoder given is {given} (sha256 {file_sha256(given)[:12]}), another model: give "
                f"{recorded['path']}, or leave the encoder out to use it"
            )
        return Path(given)
    return _find(recorded, checkpoint)


@functools.cache  # once a process: a command's check and its run both ask
def _warn_no_encoder(checkpoint: str, used: str) -> None:
    log.warning("%s records no encoder (saved before policies carried one); using %s", checkpoint, used)


def _find(recorded: dict[str, str], checkpoint: str | Path) -> Path:
    candidates = [REPO_ROOT / recorded["path"], Path(recorded["path"]), *sorted(SHIPPED_ENCODERS.glob("*.pt"))]
    for candidate in candidates:
        if candidate.is_file() and file_sha256(candidate) == recorded["sha256"]:
            return candidate
    raise FileNotFoundError(
        f"policy {checkpoint} was trained on encoder {recorded['path']} (sha256 {recorded['sha256'][:12]}), which is "
        f"not here: give its file with --encoder-checkpoint"
    )


def _shown(path: Path) -> str:
    """A path relative to the repository when inside it, so an identity reads the same on every checkout."""
    try:
        return str(path.resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)
