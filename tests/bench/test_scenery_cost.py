"""`swimm bench sim`'s in-process keys: the plain and the varied world's rates; the plain world drawn anti-aliased;
a group's with a renderer each and sharing one."""

from __future__ import annotations

import math

import pytest

from bench.sim import measure_render_scale, measure_renderers, measure_scenery


def assert_rates_and_ratio(result: dict, base: str, other: str, ratio: str) -> None:
    """Both rates measured and finite, and the ratio key the quotient of the other over the base."""
    for key in (base, other):
        assert math.isfinite(result[key]) and result[key] > 0
    assert result[ratio] == pytest.approx(result[other] / result[base], 1e-2)


def test_the_scenery_measurement_reports_both_rates_and_their_ratio() -> None:
    result = measure_scenery(steps=200)
    assert_rates_and_ratio(result, "plain_steps_per_s", "varied_steps_per_s", "varied_over_plain")


def test_the_renderer_measurement_steps_every_world_of_both_groups() -> None:
    result = measure_renderers(steps=200, envs=2)
    assert result["renderer_group_envs"] == 2
    assert_rates_and_ratio(result, "own_renderers_steps_per_s", "shared_renderer_steps_per_s",
                           "shared_over_own_renderers")  # fmt: skip


def test_the_render_scale_measurement_reports_the_scaled_rate_against_the_point_sampled_one() -> None:
    result = measure_render_scale(steps=200, scale=2)
    assert result["render_scale"] == 2
    assert_rates_and_ratio(result, "render_point_steps_per_s", "render_scaled_steps_per_s", "render_scaled_over_point")
