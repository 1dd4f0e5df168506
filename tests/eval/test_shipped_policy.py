"""The policy to fly (learner_service/models/sac_cmvae_general.zip, SHIPPED_POLICY) still tracks: a bare `swimm eval`'s
contender, on the real world with the CMVAE it records in one process, against the scripted baseline on the same
episode.

A short episode, so it guards the artefacts (a policy and an encoder that no longer fit each other, an
observation layout that changed under them) rather than measuring them; docs/eval_report.md measures.
"""

from __future__ import annotations

import pytest

from eval_service.engine import EvaluationSettings, evaluate
from learner_service.export import SHIPPED_POLICY

STEPS = 400

pytestmark = pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="no shipped policy in this checkout")


def test_the_shipped_policy_follows_the_dolphin_from_the_camera_alone(tmp_path) -> None:
    given = EvaluationSettings(backend="inprocess", obs="cmvae", algo=["scripted", "sac"], episodes=1, steps=STEPS,
                               seed=113, progress_bar=False, figures=False)  # fmt: skip
    summaries = evaluate(given, tmp_path)
    shipped, baseline = summaries["sac"], summaries["scripted"]
    assert shipped["A'"] == shipped["D'"] == shipped["C'"] == 0.0  # kept it in view, in the band, no contact
    assert shipped["mean_return"] > 0.6 * STEPS
    assert shipped["mean_return"] > 0.7 * baseline["mean_return"]
