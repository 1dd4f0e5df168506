"""Identity in a pod at hand-built cases: every expected value below is worked out by hand in its comment."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.identity import (
    NONE,
    episode_identity,
    followed_dolphin,
    in_view,
    level_camera_points,
    off_axis_deg,
    target_occluded,
)


def test_off_axis_angles():
    points = np.array([(1, 0, 0), (1, 1, 0), (0, 0, 1), (-1, 0, 0)])
    assert off_axis_deg(points) == pytest.approx([0.0, 45.0, 90.0, 180.0])


def test_a_level_rovers_camera_sees_from_its_nose():
    # The camera sits 0.235 m ahead of the rover's centre and 0.02 m above it, looking along its heading.
    rovers = np.array([(0.0, 0.0, -2.0), (1.0, 1.0, 0.0)])
    positions = np.array([
        [(0, 5, -1), (-3, 0, -2)],  # heading 90 deg (+y): 4.765 ahead, 0.98 up; 3 m to its left, 0.235 behind
        [(2, 1, 0.5), (1, 3, 0)],  # heading 0 (+x): 0.765 ahead, 0.48 up; 2 m to its left, 0.235 behind
    ])  # fmt: skip
    points = level_camera_points(rovers, np.array([90.0, 0.0]), positions)
    expected = [[(4.765, 0, 0.98), (-0.235, 3, -0.02)], [(0.765, 0, 0.48), (-0.235, 2, -0.02)]]
    np.testing.assert_allclose(points, expected, atol=1e-12)


def test_in_view_is_inside_the_image_and_in_front():
    # alpha = atan(4.98 / 5.94) = 39.98 deg, beta = atan(3.74 / 5.94) = 32.20 deg
    points = np.array([
        (1, 0.8, 0),  # azimuth atan(0.8) = 38.66: in
        (1, -0.9, 0),  # azimuth 41.99: out
        (1, 0, 0.6),  # elevation atan(0.6) = 30.96: in
        (1, 0, -0.7),  # elevation 34.99: out
        (-1, 0, 0),  # behind
    ])  # fmt: skip
    assert in_view(points).tolist() == [True, False, True, False, False]


def test_the_followed_dolphin_is_the_one_in_view_nearest_the_centre():
    target, nearer_axis, outside = (5, 1, 0), (4, -0.3, 0), (2, 5, 0)  # 11.31, 4.29 and 68.20 deg off the axis
    # The first two are 15.60 deg apart, more than their discs' asin(0.44 / 5.10) + asin(0.44 / 4.01) = 11.25 deg.
    assert followed_dolphin(np.array([target, nearer_axis, outside])) == 1
    assert followed_dolphin(np.array([target, (-4, 0, 0), outside])) == 0  # the one nearer the axis is behind
    assert followed_dolphin(np.array([(2, 5, 0), (-4, 0, 0)])) == NONE
    # 1.27 deg off the axis but behind the target (4.76 deg): 3.49 deg apart, within their discs' 4.19 + 2.80 deg.
    assert followed_dolphin(np.array([(6, 0.5, 0), (9, 0.2, 0)])) == 0


def test_a_companion_occludes_the_target_when_nearer_and_overlapping():
    # Discs of 0.44 m: at 3 m asin(0.44 / 3) = 8.43 deg, at 6 m asin(0.44 / 6) = 4.21 deg; together 12.64 deg.
    target = (6, 0, 0)
    assert target_occluded(np.array([target, (3, 0.5, 0)]))  # atan(0.5 / 3) = 9.46 deg apart
    assert not target_occluded(np.array([target, (3, 1, 0)]))  # 18.43 deg apart
    assert not target_occluded(np.array([target, (9, 0, 0)]))  # on the line, but behind the target
    assert target_occluded(np.array([target, (9, 0, 0), (3, 0.5, 0)]))  # any companion will do
    assert not target_occluded(np.array([target]))  # a lone dolphin


def test_an_episode_with_a_crossing_re_acquired_at_once_and_a_switch_away_and_back():
    followed = [0, 0, 1, 1, 0, 0, 2, 0, NONE, 0]
    occluded = [False, False, True, True, False, False, False, False, False, False]
    # Unoccluded steps 0, 1, 4-9 follow 0, 0, 0, 0, 2, 0, none, 0: 6 of 8 on the target. Without the none: 0 0 0 0 2 0
    # 0, two changes. One occlusion, over at step 4, where the target is followed at once.
    assert episode_identity(followed, occluded) == {
        "identity_share": 0.75, "identity_kept": False, "switches": 2, "occlusions": 1, "reacquire_steps": 0.0,
        "unrecovered": 0,
    }  # fmt: skip


def test_re_acquiring_after_an_occlusion_takes_the_steps_to_the_target():
    # The occlusion at step 1 is over at step 2; the target is followed again at step 5: 3 steps. Unoccluded steps
    # follow 0, 1, 1, 1, 0: 2 of 5 on the target, switches 0 -> 1 -> 0.
    row = episode_identity([0, 1, 1, 1, 1, 0], [False, True, False, False, False, False])
    assert row == {"identity_share": 0.4, "identity_kept": False, "switches": 2, "occlusions": 1,
                   "reacquire_steps": 3.0, "unrecovered": 0}  # fmt: skip


def test_a_target_never_followed_again_is_unrecovered():
    row = episode_identity([0, 0, 2, 2], [False, True, False, False])  # 1 of 3 unoccluded steps, one switch
    assert row["identity_share"] == pytest.approx(1 / 3) and row["switches"] == 1
    assert (row["occlusions"], row["unrecovered"]) == (1, 1) and math.isnan(row["reacquire_steps"])


def test_an_occlusion_still_on_at_the_end_is_not_counted_and_nine_in_ten_keeps_identity():
    row = episode_identity([0, 1], [False, True])
    assert (row["identity_share"], row["occlusions"], row["switches"]) == (1.0, 0, 0)
    row = episode_identity([0] * 9 + [1], [False] * 10)  # 9 of 10: the threshold itself
    assert (row["identity_share"], row["identity_kept"], row["switches"]) == (0.9, True, 1)


def test_steps_must_pair_up():
    with pytest.raises(ValueError, match="need as many followed as occluded steps"):
        episode_identity([0, 0], [False])
    with pytest.raises(ValueError, match="at least one"):
        episode_identity([], [])
