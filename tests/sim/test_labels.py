"""Dataset labels against what the camera sees: the dolphin's pixels, from MuJoCo's segmentation render."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.geometry import ALPHA_DEG, CAMERA_AHEAD_M, camera_centred
from sim_service.dataset import SamplingRanges, labels_and_pose, sample_pose
from sim_service.settings import WorldSettings
from sim_service.world import World

SIZE = 64
FOCAL_PX = (SIZE / 2) / math.tan(math.radians(ALPHA_DEG))  # the pinhole's focal length in pixels


def column_azimuth(u: float) -> float:
    """The azimuth (deg, + = left) of a pixel column's centre line."""
    return math.degrees(math.atan(((SIZE - 1) / 2 - u) / FOCAL_PX))


def camera_azimuth(telemetry) -> float:
    """The target centre's azimuth seen from the camera rather than from the rover's centre."""
    rover_yaw = math.degrees(math.atan2(telemetry.rover_forward[1], telemetry.rover_forward[0]))
    _, azimuth = camera_centred(np.asarray(telemetry.rover_pos[:2]), rover_yaw, np.asarray(telemetry.target_pos[:2]))
    return float(azimuth)


@pytest.fixture(scope="module")
def views():
    """(labels, camera-centred azimuth, dolphin mask) of 150 dataset samples whose dolphin is wholly in frame."""
    world = World(WorldSettings(image_size=SIZE))
    found = []
    try:
        for index in range(200):
            telemetry, _ = sample_pose(world, np.random.default_rng([5, index]), SamplingRanges())
            mask = world.target_mask()
            columns = np.flatnonzero(mask.any(axis=0))
            if len(columns) and columns[0] > 0 and columns[-1] < SIZE - 1:
                found.append((labels_and_pose(telemetry)[0], camera_azimuth(telemetry), mask))
    finally:
        world.close()
    assert len(found) > 100
    return found


def test_the_azimuth_label_lies_within_the_dolphins_pixels(views) -> None:
    for labels, seen_from_camera, mask in views:
        columns = np.flatnonzero(mask.any(axis=0))
        right_edge, left_edge = column_azimuth(columns[-1] + 0.5), column_azimuth(columns[0] - 0.5)
        assert right_edge <= labels[1] <= left_edge
        assert right_edge <= seen_from_camera <= left_edge


def test_the_dolphins_pixels_centre_on_the_camera_centred_azimuth(views) -> None:
    """The mask's centroid is not the body centre's projection (head and tail differ), so this holds on average."""
    centroid_errors, label_errors = [], []
    for labels, seen_from_camera, mask in views:
        weights = mask.sum(axis=0)
        centroid = column_azimuth(float((weights * np.arange(SIZE)).sum() / weights.sum()))
        centroid_errors.append(abs(centroid - seen_from_camera))
        label_errors.append(abs(centroid - labels[1]))
    assert np.median(centroid_errors) < 1.5
    # The rover-centred label (the SPEC's) sits up to a few degrees off what the camera sees, never more.
    assert np.max(np.abs(np.subtract(label_errors, centroid_errors))) < 5.0


def test_the_mask_needs_a_rendering_world() -> None:
    world = World(WorldSettings(render=False))
    try:
        with pytest.raises(RuntimeError, match="rendering world"):
            world.target_mask()
    finally:
        world.close()


def test_the_camera_offset_is_the_models_nose_camera() -> None:
    world = World(WorldSettings(image_size=SIZE))
    try:
        assert world.model.camera("nose").pos[0] == pytest.approx(CAMERA_AHEAD_M)
    finally:
        world.close()
