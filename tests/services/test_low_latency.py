"""What one low-latency message carries: the largest image and the largest group of observations that fit, and
the refusal that names the largest group when asked for more (that transport cannot fragment)."""

from __future__ import annotations

import pytest

from services.low_latency import (
    check_low_latency_group,
    largest_low_latency_group,
    largest_low_latency_image_size,
    low_latency_group_problem,
    observation_bytes,
)
from services.session import LOW_LATENCY_MAX_MESSAGE_BYTES

IMAGE_SIZE = 64  # the sim's default frame (sim_service.settings.WorldSettings.image_size)


def test_the_largest_low_latency_group_is_the_most_observations_one_message_holds() -> None:
    largest = largest_low_latency_group(IMAGE_SIZE)
    assert largest * observation_bytes(IMAGE_SIZE) <= LOW_LATENCY_MAX_MESSAGE_BYTES
    assert (largest + 1) * observation_bytes(IMAGE_SIZE) > LOW_LATENCY_MAX_MESSAGE_BYTES
    assert low_latency_group_problem(largest, IMAGE_SIZE) is None
    problem = low_latency_group_problem(largest + 1, IMAGE_SIZE)
    assert f"--group-size {largest} or less" in problem and "--low-latency" in problem
    assert largest_low_latency_group(IMAGE_SIZE // 2) > largest  # smaller frames, bigger groups


def test_the_largest_image_is_the_largest_square_whose_observation_fits() -> None:
    largest = largest_low_latency_image_size()
    assert observation_bytes(largest) <= LOW_LATENCY_MAX_MESSAGE_BYTES < observation_bytes(largest + 1)
    assert largest == 123  # 45 387 image bytes plus the overhead fit in 48 000; 124 px do not


def test_checking_a_group_returns_the_largest_or_refuses_by_name() -> None:
    largest = largest_low_latency_group(IMAGE_SIZE)
    assert check_low_latency_group(0, IMAGE_SIZE) == check_low_latency_group(largest, IMAGE_SIZE) == largest
    with pytest.raises(ValueError, match=f"--group-size {largest} or less"):
        check_low_latency_group(largest + 1, IMAGE_SIZE)
