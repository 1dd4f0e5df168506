"""How `swimm up` lays envs out in groups: one group per sim, or the largest whole part of it that a low-latency
message carries (that transport cannot fragment, so a larger group's reply would be lost without an error)."""

from __future__ import annotations

import dataclasses

import pytest

from learner_service.up import UpSettings, group_size_for, largest_whole_group, run
from services.low_latency import largest_low_latency_group
from sim_service.settings import WorldSettings

IMAGE_SIZE = WorldSettings().image_size


@pytest.mark.parametrize(("share", "largest", "whole"), [(4, 4, 4), (4, 3, 2), (6, 3, 3), (6, 5, 3), (5, 3, 1)])
def test_the_largest_whole_group_divides_a_sims_share_and_fits(share: int, largest: int, whole: int) -> None:
    assert largest_whole_group(share, largest) == whole


def test_one_group_per_sim_shrinks_to_fit_a_low_latency_message() -> None:
    assert group_size_for(8, 0, 2) == 4
    assert group_size_for(8, 0, 2, largest_group=3) == 2
    assert group_size_for(8, 2, 2, largest_group=3) == 2  # as asked, when it fits


def test_up_refuses_a_group_too_large_for_low_latency_before_starting_anything(tmp_path) -> None:
    largest = largest_low_latency_group(IMAGE_SIZE)
    defaults = UpSettings()
    learn = dataclasses.replace(
        defaults.learn,
        envs=2 * (largest + 1),
        group_size=largest + 1,
        run_dir=str(tmp_path / "run"),
        zenoh=dataclasses.replace(defaults.learn.zenoh, low_latency=True),
    )
    with pytest.raises(ValueError, match=f"--group-size {largest} or less"):
        run(dataclasses.replace(defaults, learn=learn, sims=2))
    assert not (tmp_path / "run").exists()
