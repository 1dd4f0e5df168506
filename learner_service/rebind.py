"""`swimm rebind`: a copy of a trained policy that flies on another CMVAE, saying so in its identity.

A policy records the CMVAE it trained on, and every command refuses another (learner_service/identity.py). A
fine-tune of that CMVAE writes latents the policy still reads (the policy to fly trained on `cmvae_wide.pt` and flies
on its fine-tune `cmvae_fans.pt`; docs/learner.md, "One policy to fly"), but only an evaluation can say it does. This
command writes the copy that the evaluation and everything after it use: the same weights, the new encoder as the
one it flies on, and the encoder it trained on kept beside it as ``trained_on``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from encoder_service.model import read_checkpoint
from learner_service.identity import LEGACY_TASK, TRAINED_ON_KEY, encoder_for, policy_identity, read_identity, stamp
from learner_service.registry import resolve_algorithm
from services.results import file_sha256

log = logging.getLogger(__name__)


@dataclass
class RebindSettings:
    checkpoint: str = ""  # the policy (a model zip that records its CMVAE, as `swimm learn` saves)
    encoder_checkpoint: str = ""  # the CMVAE the copy flies on: a fine-tune of the one the policy records
    out: str = ""  # the copy
    algo: str = "sac"  # the algorithm that saved --checkpoint
    overwrite: bool = False  # replace an existing --out


def check(settings: RebindSettings) -> None:
    """Refuse, naming the flag, whatever would make the copy wrong, before writing anything."""
    for flag, value in (("--checkpoint", settings.checkpoint), ("--encoder-checkpoint", settings.encoder_checkpoint),
                        ("--out", settings.out)):  # fmt: skip
        if not value:
            raise ValueError(
                f"{flag} is required: swimm rebind --checkpoint POLICY --encoder-checkpoint CMVAE --out COPY"
            )
    resolve_algorithm(settings.algo)
    identity = read_identity(settings.checkpoint)
    recorded = (identity or {}).get("encoder")
    if recorded is None:
        raise ValueError(
            f"--checkpoint {settings.checkpoint} records no CMVAE: only a policy on latents can fly on another"
        )
    new_encoder = read_checkpoint(settings.encoder_checkpoint)
    if file_sha256(settings.encoder_checkpoint) == recorded["sha256"]:
        raise ValueError(f"--encoder-checkpoint {settings.encoder_checkpoint} is the CMVAE the policy already records")
    trained_on = read_checkpoint(encoder_for(settings.checkpoint, None))  # refuses, naming it, one not here
    if new_encoder["config"]["n_z"] != trained_on["config"]["n_z"]:
        raise ValueError(
            f"--encoder-checkpoint {settings.encoder_checkpoint} writes {new_encoder['config']['n_z']} latents, but "
            f"{recorded['path']}, which the policy records, writes {trained_on['config']['n_z']}: only a fine-tune of "
            f"it fits"
        )
    if Path(settings.out).resolve() == Path(settings.checkpoint).resolve():
        raise ValueError(f"--out {settings.out} is --checkpoint: the copy must not replace the policy it copies")
    if Path(settings.out).exists() and not settings.overwrite:
        raise FileExistsError(f"--out {settings.out} exists: give --overwrite to replace it, or choose another --out")


def rebind(checkpoint: str | Path, encoder: str | Path, out: str | Path, algo: str = "sac") -> Path:
    """Write ``checkpoint``'s policy to ``out``, recording ``encoder`` as its CMVAE and the one it trained on as
    ``trained_on`` (the first one, when ``checkpoint`` is itself a copy)."""
    identity = read_identity(checkpoint)
    task = identity["task"]
    cls, _ = resolve_algorithm(algo)
    model = cls.load(checkpoint, device="cpu")
    copy = policy_identity(encoder, task["obs"], task["reward"], task.get("name", LEGACY_TASK))
    copy[TRAINED_ON_KEY] = identity.get(TRAINED_ON_KEY, identity["encoder"])
    stamp(model, copy)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    model.save(out)
    log.info("wrote %s: %s's policy, trained on %s, flying on %s", out, checkpoint, copy[TRAINED_ON_KEY]["path"],
             copy["encoder"]["path"])  # fmt: skip
    return out


def run(settings: RebindSettings) -> None:
    check(settings)
    rebind(settings.checkpoint, settings.encoder_checkpoint, settings.out, settings.algo)
