"""Behaviour metrics: the SPEC's smoothness example and hand-computed episode rows and summaries."""

from __future__ import annotations

import numpy as np
import pytest

from learner_service.metrics import (
    IDENTITY_COLUMNS,
    SUMMARY_ROW_FIELDS,
    VERTICAL_ROW_FIELDS,
    EpisodeMetrics,
    smoothness,
    summarise,
)
from services.geometry import ALPHA_DEG, BETA_DEG, MAX_D, OPT_D
from services.identity import IDENTITY_ROW_FIELDS


def test_the_papers_worked_example_with_surge_first() -> None:
    # ActPrev oldest first; actions are (surge, yaw). Surge: 0.5 * (0.1*0.25 + 0.5*0.20 + 1.5*0.15) = 0.175;
    # yaw: 0.5 * (0*0.25 + 0.2*0.20 + 0.3*0.15) = 0.0425. The other assignment would not reproduce both numbers.
    s = smoothness([(-1.0, 0.5), (1.0, 0.0), (0.4, 0.2)], (0.5, 0.2))
    assert s[0] == pytest.approx(1.75e-1)  # S_D
    assert s[1] == pytest.approx(4.25e-2)  # S_A


def test_smoothness_uses_only_the_last_ten_actions() -> None:
    # 11 previous actions: the oldest (far away) must not count; the other ten differ by 1, weights sum to 1.
    history = [(100.0, 100.0)] + [(0.0, 1.0)] * 10
    np.testing.assert_allclose(smoothness(history, (1.0, 0.0)), [0.5, 0.5])
    np.testing.assert_array_equal(smoothness([], (0.3, -0.3)), [0.0, 0.0])
    # one previous action: only W_1 = 0.25 applies
    np.testing.assert_allclose(smoothness([(0.0, 0.0)], (1.0, -0.4)), [0.125, 0.05])


def test_episode_row_from_hand_computed_steps() -> None:
    metrics = EpisodeMetrics(label="sac", episode=3)
    steps = [
        # d, theta, in_frustum, collided, action, reward
        (6.0, 0.0, True, False, (0.0, 0.0), 1.0),
        (8.0, 20.0, True, False, (1.0, 0.0), 0.5),
        (11.0, 80.0, False, False, (1.0, 1.0), -1.0),
        (4.0, 10.0, True, True, (0.0, 1.0), 0.0),
    ]
    per_step = [tuple(metrics.add(*step).values()) for step in steps]
    # smoothness (s_d, s_a): step 1 none; step 2: 0.5*1*0.25; step 3: s_d 0.5*(0*0.25 + 1*0.2), s_a 0.5*1*(0.25+0.2);
    # step 4: s_d 0.5*(1*0.25 + 1*0.2 + 0*0.15), s_a 0.5*(0*0.25 + 1*0.2 + 1*0.15)
    expected_steps = [(0.0, 0.0), (0.125, 0.0), (0.1, 0.225), (0.225, 0.175)]
    np.testing.assert_allclose(per_step, expected_steps)
    row = metrics.row()
    assert tuple(row) == SUMMARY_ROW_FIELDS
    assert row["label"] == "sac" and row["episode"] == 3
    assert row["return"] == pytest.approx(0.5)
    # A: (0 + 20/alpha + 1 (capped) + 10/alpha) / 4
    assert row["A"] == pytest.approx((30.0 / ALPHA_DEG + 1.0) / 4)
    # D: (0 + 2/4 + 5/4 (uncapped) + 2/4) / 4
    assert row["D"] == pytest.approx(2.25 / 4)
    assert row["left_view"] is True and row["distance_exceeded"] is True and row["collided"] is True
    assert row["first_cause"] == "visibility"  # step 3 left the view (and the distance band) first: most severe wins
    assert row["S_D"] == pytest.approx((0.125 + 0.1 + 0.225) / 4)
    assert row["S_A"] == pytest.approx((0.225 + 0.175) / 4)


def test_a_clean_episode_has_no_violation() -> None:
    metrics = EpisodeMetrics("scripted", 1)
    for _ in range(3):
        metrics.add(7.0, 5.0, True, False, (0.2, -0.2), 0.9)
    row = metrics.row()
    assert (row["left_view"], row["distance_exceeded"], row["collided"], row["first_cause"]) == (
        False,
        False,
        False,
        "",
    )
    assert row["S_D"] == 0.0 and row["S_A"] == 0.0
    assert row["D"] == pytest.approx(0.25)
    assert row["A"] == pytest.approx(5.0 / ALPHA_DEG)
    with pytest.raises(ValueError, match="no steps"):
        EpisodeMetrics("empty", 2).row()


def test_summary_over_episodes() -> None:
    rows = [
        {
            "return": 100.0,
            "A": 0.1,
            "D": 0.2,
            "left_view": True,
            "distance_exceeded": False,
            "collided": False,
            "S_D": 0.01,
            "S_A": 0.02,
        },
        {
            "return": 300.0,
            "A": 0.3,
            "D": 0.4,
            "left_view": True,
            "distance_exceeded": True,
            "collided": False,
            "S_D": 0.03,
            "S_A": 0.04,
        },
        {
            "return": -100.0,
            "A": 0.2,
            "D": 0.0,
            "left_view": False,
            "distance_exceeded": False,
            "collided": True,
            "S_D": 0.05,
            "S_A": 0.06,
        },
        {
            "return": 100.0,
            "A": 0.2,
            "D": 0.2,
            "left_view": False,
            "distance_exceeded": False,
            "collided": False,
            "S_D": 0.01,
            "S_A": 0.0,
        },
    ]
    summary = summarise(rows)
    assert summary["episodes"] == 4
    assert summary["A"] == pytest.approx(0.2)
    assert summary["D"] == pytest.approx(0.2)
    assert summary["A'"] == pytest.approx(0.5)
    assert summary["D'"] == pytest.approx(0.25)
    assert summary["C'"] == pytest.approx(0.25)
    assert summary["S_D"] == pytest.approx(0.025)
    assert summary["S_A"] == pytest.approx(0.03)
    assert summary["mean_return"] == pytest.approx(100.0)
    assert summary["std_return"] == pytest.approx(np.sqrt((0 + 200**2 + 200**2 + 0) / 4))


def test_3d_episodes_add_the_mean_elevation_error_normalised_as_a_is() -> None:
    metrics = EpisodeMetrics("3d", 1)
    for phi in (0.0, 10.0, 50.0):  # the last one capped at beta
        metrics.add(6.0, 0.0, True, False, (0.0, 0.0, 0.0), 1.0, phi)
    row = metrics.row()
    assert tuple(row) == SUMMARY_ROW_FIELDS + VERTICAL_ROW_FIELDS
    assert row["E"] == pytest.approx((10.0 / BETA_DEG + 1.0) / 3)
    other = EpisodeMetrics("3d", 2)
    other.add(6.0, 0.0, True, False, (0.0, 0.0, 0.0), 1.0, BETA_DEG / 2)
    assert summarise([metrics, other])["E"] == pytest.approx((row["E"] + 0.5) / 2)
    planar = EpisodeMetrics("planar", 1)
    planar.add(6.0, 0.0, True, False, (0.0, 0.0), 1.0)
    assert "E" not in planar.row() and "E" not in summarise([planar])


def test_3d_actions_add_heave_smoothness_computed_as_surge_and_yaw_are() -> None:
    """(surge, heave, yaw): S_D of component 0, S_H of 1, S_A of 2, each as the planar task's components."""
    metrics = EpisodeMetrics("3d", 1)
    steps = [metrics.add(6.0, 0.0, True, False, action, 1.0, 0.0) for action in [(0.0, 0.0, 0.0), (1.0, -1.0, 0.5)]]
    assert steps[1] == pytest.approx({"S_D": 0.125, "S_A": 0.0625, "S_H": 0.125})  # 0.5 * |change| * W_1 (0.25)
    row = metrics.row()
    assert (row["S_D"], row["S_H"], row["S_A"]) == pytest.approx((0.0625, 0.0625, 0.03125))
    assert summarise([row])["S_H"] == pytest.approx(0.0625)
    planar = EpisodeMetrics("planar", 1)
    assert "S_H" not in planar.add(6.0, 0.0, True, False, (1.0, 0.5), 1.0)
    assert "S_H" not in planar.row() and "S_H" not in summarise([planar])


def test_summary_accepts_accumulators_and_refuses_nothing() -> None:
    metrics = EpisodeMetrics("x", 1)
    metrics.add(6.0, 0.0, True, False, (0.0, 0.0), 2.0)
    assert summarise([metrics])["mean_return"] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="no episodes"):
        summarise([])


def test_boundaries_of_the_violation_flags_and_the_azimuth_cap() -> None:
    # D' is |d - opt_d| >= max_d (the SPEC's threshold counts), on either side of opt_d; A caps |theta| at alpha.
    at_far_edge = EpisodeMetrics("edge", 1)
    at_far_edge.add(OPT_D + MAX_D, -ALPHA_DEG, True, False, (0.0, 0.0), 0.0)
    row = at_far_edge.row()
    assert row["distance_exceeded"] is True and row["first_cause"] == "distance"
    assert row["A"] == pytest.approx(1.0) and row["D"] == pytest.approx(1.0)
    just_inside = EpisodeMetrics("inside", 1)
    just_inside.add(OPT_D - MAX_D + 1e-9, -3 * ALPHA_DEG, True, False, (0.0, 0.0), 0.0)
    row = just_inside.row()
    assert row["distance_exceeded"] is False and row["first_cause"] == ""
    assert row["A"] == pytest.approx(1.0)  # a negative azimuth error counts by its size, capped


def test_a_pods_steps_add_identity_to_the_row_and_its_episodes_to_the_summary() -> None:
    metrics = EpisodeMetrics(label="sac", episode=1)
    # (followed, target occluded): unoccluded steps 0, 2, 3 follow 0, 0, 2: 2 of 3 on the target, one switch; the
    # occlusion at step 1 is over at step 2, where the target is followed at once.
    for identity in ((0, False), (1, True), (0, False), (2, False)):
        metrics.add(6.0, 0.0, True, False, (0.0, 0.0), 1.0, identity=identity)
    row = metrics.row()
    assert tuple(row) == SUMMARY_ROW_FIELDS + IDENTITY_ROW_FIELDS
    assert row["identity_share"] == pytest.approx(2 / 3) and row["identity_kept"] is False
    assert (row["switches"], row["occlusions"], row["reacquire_steps"], row["unrecovered"]) == (1, 1, 0.0, 0)
    kept = row | {"identity_share": 1.0, "identity_kept": True, "switches": 0, "reacquire_steps": float("nan")}
    lost = row | {"identity_share": 0.5, "identity_kept": False, "switches": 3, "reacquire_steps": 4.0}
    summary = summarise([kept, lost])
    # one episode of two kept identity; the NaN of an episode with nothing to re-acquire is left out of the mean
    assert {name: summary[name] for name in IDENTITY_COLUMNS} == {
        "identity_kept": 0.5, "identity_share": 0.75, "switches": 1.5, "reacquire_steps": 4.0,
    }  # fmt: skip

    lone = EpisodeMetrics(label="sac", episode=1)  # a lone dolphin's steps carry no identity to keep
    lone.add(6.0, 0.0, True, False, (0.0, 0.0), 1.0)
    assert tuple(lone.row()) == SUMMARY_ROW_FIELDS and not set(IDENTITY_COLUMNS) & set(summarise([lone]))
