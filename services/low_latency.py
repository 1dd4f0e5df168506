"""What one message of Zenoh's low-latency transport can carry: observations of a given image size, and groups
of them. That transport cannot fragment (services.session.LOW_LATENCY_MAX_MESSAGE_BYTES), so the sim, the
launcher and the benches check their sizes against these before anything starts."""

from __future__ import annotations

import functools
import math

from services.session import LOW_LATENCY_MAX_MESSAGE_BYTES

#: Room allowed for what an observation carries besides its image (stamps, telemetry, field names): 505 to
#: 523 bytes encoded, measured.
OBSERVATION_OVERHEAD_BYTES = 2048


def observation_bytes(image_size: int) -> int:
    """The most an observation of ``image_size`` px takes encoded: its RGB image and the room for the rest."""
    return 3 * image_size**2 + OBSERVATION_OVERHEAD_BYTES


def largest_low_latency_image_size() -> int:
    """The largest square RGB image whose observation a low-latency session can send."""
    return math.isqrt((LOW_LATENCY_MAX_MESSAGE_BYTES - OBSERVATION_OVERHEAD_BYTES) // 3)


def largest_low_latency_group(image_size: int) -> int:
    """The most observations of ``image_size`` px that one low-latency message (a group's reply) can carry."""
    return LOW_LATENCY_MAX_MESSAGE_BYTES // observation_bytes(image_size)


@functools.cache  # the sim asks on every step
def low_latency_group_problem(group_size: int, image_size: int) -> str | None:
    """Why a group of ``group_size`` observations cannot cross a low-latency session as one message, or None.

    That transport cannot fragment: a larger message is lost without an error on either side.
    """
    largest = largest_low_latency_group(image_size)
    if group_size <= largest:
        return None
    size = group_size * observation_bytes(image_size)
    return (
        f"a group of {group_size} observations of {image_size} px takes up to {size} bytes, more than the "
        f"{LOW_LATENCY_MAX_MESSAGE_BYTES} that --low-latency sends in one message: use "
        f"--group-size {largest} or less, or leave --low-latency off"
    )


def check_low_latency_group(group_size: int, image_size: int) -> int:
    """Refuse a ``group_size`` too large for one low-latency message; the largest group that fits."""
    if problem := low_latency_group_problem(group_size, image_size):
        raise ValueError(problem)
    return largest_low_latency_group(image_size)
