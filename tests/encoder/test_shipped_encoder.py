"""The shipped CMVAEs still score, on frames they have never seen, what docs/encoder/ says they score.

A guard on the committed model and on the sim that renders for it: 400 fresh frames from the held-out
generator (seed 5, as in docs/encoder.md) must give errors close to the documented ones, measured by
`swimm eval-encoder` on 5000 frames. The tolerances cover the sampling error of 400 frames; a model or a
renderer that changed what the latents mean would miss them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from encoder_service.data import CMVAEDataset
from encoder_service.inference import DEFAULT_CHECKPOINT, LatentEncoder
from encoder_service.model import label_errors

DOCUMENTED = Path(__file__).resolve().parents[2] / "docs" / "encoder" / "metrics.json"
TOLERANCE = {"d_m": 0.06, "theta_deg": 0.25, "psi_deg": 8.0}


def _mae(encoder: LatentEncoder, folder: Path) -> dict[str, float]:
    """The encoder's MAE of d, theta and psi over every frame of a dataset folder."""
    frames = CMVAEDataset(folder)
    batch = frames.read(np.arange(len(frames)))
    mu, _ = encoder.encode(batch.images)
    errors = label_errors(np.stack(encoder.decode_state(mu), axis=1), batch.labels).mean(axis=0)
    return dict(zip(("d_m", "theta_deg", "psi_deg"), (float(e) for e in errors), strict=True))


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped CMVAE in this checkout")
def test_the_shipped_cmvae_scores_its_documented_errors_on_fresh_frames(tmp_path: Path) -> None:
    from sim_service.dataset import write_dataset

    documented = json.loads(DOCUMENTED.read_text())
    assert Path(documented["checkpoint"]).name == DEFAULT_CHECKPOINT.name and documented["dataset_seed"] == 5
    held_out = write_dataset(tmp_path / "held-out", count=400, seed=5, progress=False)
    measured = _mae(LatentEncoder(DEFAULT_CHECKPOINT), held_out)
    for name, tolerance in TOLERANCE.items():
        assert measured[name] == pytest.approx(documented["mae"][name], abs=tolerance), (name, measured)


#: The noise-robust CMVAEs and their documented scores: the shipped one, and the one before it, which the slow-loop
#: policy reads.
ROBUST = {
    DEFAULT_CHECKPOINT.with_name("cmvae_robust.pt"): DOCUMENTED.parent / "noise" / "robust-murky.json",
    DEFAULT_CHECKPOINT.with_name("cmvae_mixture.pt"): DOCUMENTED.parent / "noise" / "mixture-murky.json",
}
MURKY_TOLERANCE = {"d_m": 0.12, "theta_deg": 0.4, "psi_deg": 10.0}  # noisier errors: a wider sampling spread


@pytest.mark.parametrize("checkpoint", list(ROBUST), ids=lambda path: path.stem)
def test_a_noise_robust_cmvae_scores_its_documented_errors_on_fresh_clean_and_murky_frames(
    tmp_path: Path, checkpoint: Path
) -> None:
    from sim_service.dataset import write_dataset
    from sim_service.noise import NoiseSettings
    from sim_service.settings import WorldSettings

    if not checkpoint.is_file():
        pytest.skip(f"no {checkpoint.name} in this checkout")
    documented = json.loads(ROBUST[checkpoint].read_text())
    assert Path(documented["checkpoint"]).name == checkpoint.name and documented["dataset_seed"] == 5
    encoder = LatentEncoder(checkpoint)
    murky = WorldSettings(noise=NoiseSettings(preset="murky"))
    for name, world, expected, tolerance in (
        ("clean", None, documented["mae"], TOLERANCE),
        ("murky", murky, documented["noisy"]["mae"], MURKY_TOLERANCE),
    ):
        measured = _mae(
            encoder, write_dataset(tmp_path / name, count=400, seed=5, world_settings=world, progress=False)
        )
        for label, allowed in tolerance.items():
            assert measured[label] == pytest.approx(expected[label], abs=allowed), (name, label, measured)
