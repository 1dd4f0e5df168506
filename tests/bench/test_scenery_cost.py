"""`swimm bench sim`'s scenery keys: the plain and the varied world's in-process rates and their ratio."""

from __future__ import annotations

import math

import pytest

from bench.sim import measure_scenery


def test_the_scenery_measurement_reports_both_rates_and_their_ratio() -> None:
    result = measure_scenery(steps=200)
    for key in ("plain_steps_per_s", "varied_steps_per_s"):
        assert math.isfinite(result[key]) and result[key] > 0
    assert result["varied_over_plain"] == pytest.approx(
        result["varied_steps_per_s"] / result["plain_steps_per_s"], 1e-2
    )
