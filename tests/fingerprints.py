"""Shipped models told apart: each one's outputs on fixed inputs, measured once and recorded in its test, must
match its own record and no other shipped model's (tests/encoder/test_shipped_encoder.py, tests/eval/
test_shipped_policy.py)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np


def matches(outputs: np.ndarray, recorded: Sequence, tolerance: float | Sequence[float]) -> bool:
    """Whether ``outputs`` equal ``recorded`` within ``tolerance`` (one value, or one per output column) everywhere."""
    expected = np.asarray(recorded)
    return outputs.shape == expected.shape and bool(np.all(np.abs(outputs - expected) <= np.asarray(tolerance)))


def check_pairing(
    outputs: Mapping[str, np.ndarray],
    records: Mapping[str, Sequence],
    tolerance: float | Sequence[float],
    candidate: str,
    expected: str,
) -> None:
    """``candidate``'s outputs match ``expected``'s record exactly when they are the same model."""
    assert matches(outputs[candidate], records[expected], tolerance) == (candidate == expected), (
        f"{candidate} gave {np.round(outputs[candidate], 4).tolist()}; {expected} gives {records[expected]}"
    )
