"""The benchmarks' layout of several envs: two sims from 4 envs, one group per sim, smaller under --low-latency."""

from __future__ import annotations

import pytest

from bench.layout import default_layout
from services.low_latency import largest_low_latency_group
from sim_service.settings import WorldSettings


def test_from_four_envs_two_sims_each_step_one_group() -> None:
    assert default_layout(8) == (2, 4)
    assert default_layout(2) == (1, 0)
    assert default_layout(8, group_size=2) == (2, 2)


def test_low_latency_groups_are_the_largest_whole_part_of_a_share_that_one_message_carries() -> None:
    largest = largest_low_latency_group(WorldSettings().image_size)
    sims, group_size = default_layout(8, low_latency=True)
    assert sims == 2 and group_size <= largest and 4 % group_size == 0
    with pytest.raises(ValueError, match=f"--group-size {largest} or less"):
        default_layout(2 * (largest + 1), group_size=largest + 1, low_latency=True)
