"""The shipped CMVAE still scores, on frames it has never seen, what docs/encoder/metrics.json says it scores.

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


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped CMVAE in this checkout")
def test_the_shipped_cmvae_scores_its_documented_errors_on_fresh_frames(tmp_path: Path) -> None:
    from sim_service.dataset import write_dataset

    documented = json.loads(DOCUMENTED.read_text())
    assert Path(documented["checkpoint"]).name == DEFAULT_CHECKPOINT.name and documented["dataset_seed"] == 5
    frames = CMVAEDataset(write_dataset(tmp_path / "held-out", count=400, seed=5, progress=False))
    batch = frames.read(np.arange(len(frames)))
    encoder = LatentEncoder(DEFAULT_CHECKPOINT)
    mu, _ = encoder.encode(batch.images)
    predicted = np.stack(encoder.decode_state(mu), axis=1)
    errors = label_errors(predicted, batch.labels).mean(axis=0)
    measured = dict(zip(("d_m", "theta_deg", "psi_deg"), errors, strict=True))
    for name, tolerance in TOLERANCE.items():
        assert measured[name] == pytest.approx(documented["mae"][name], abs=tolerance), (name, measured)
