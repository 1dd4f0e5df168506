"""The pod tracker: the target chosen at engagement and held through a companion passing in front of it."""

from __future__ import annotations

import numpy as np
import pytest

from services.detections import Detections, local_maxima, pixel_looks, read_peaks
from services.pod_tracker import (
    BEHIND,
    FIELDS,
    LOOK,
    LOOK_READS,
    MAX_TRACKS,
    STATE_SIZE,
    TARGET,
    UNSEEN,
    PodTracker,
    TargetReader,
    TrackerParams,
)


def frame(*dolphins: tuple[float, float]) -> Detections:
    """Detections of dolphins at (azimuth deg, distance m), all level, all sure."""
    azimuth = np.array([a for a, _ in dolphins], float)
    distance = np.array([d for _, d in dolphins], float)
    return Detections(np.ones(len(dolphins)), azimuth, np.zeros(len(dolphins)), distance)


def run(tracker: PodTracker, frames: list[Detections]) -> tuple[np.ndarray, list]:
    state, readings = None, []
    for detections in frames:
        state, reading = tracker.update(state, detections)
        readings.append(reading)
    return state, readings


def test_engages_on_the_dolphin_nearest_the_image_centre() -> None:
    state, readings = run(PodTracker(), [frame((12.0, 5.0), (-3.0, 7.0), (20.0, 4.0))])
    assert state.shape == (STATE_SIZE,)
    assert readings[0] == pytest.approx((7.0, -3.0))
    tracks = state.reshape(MAX_TRACKS, len(FIELDS))
    assert tracks[:, TARGET].sum() == 1


def test_an_operator_can_point_the_engagement_elsewhere() -> None:
    """``engage_deg`` (the pilot's --target-box) engages the dolphin nearest that bearing, then holds it as ever."""
    pod = frame((12.0, 5.0), (-3.0, 7.0), (20.0, 4.0))
    state, first = PodTracker().update(None, pod, engage_deg=18.0)
    assert first == pytest.approx((4.0, 20.0))
    assert PodTracker().update(state, pod)[1] == pytest.approx((4.0, 20.0))  # the engagement is over: kept


def test_the_reader_tracks_frame_by_frame_through_any_runtime_and_starts_afresh_on_reset() -> None:
    """TargetReader: a detector's (heat, regression) per frame read as peaks (3x3 local maxima above the threshold,
    placed by their offsets) and tracked; UNSEEN until a dolphin shows; reset engages again."""
    grid, stride = 16, 4
    heat = np.zeros((1, grid, grid), np.float32)
    regression = np.zeros((1, 3, grid, grid), np.float32)
    for (iy, ix), distance in (((8, 3), 5.0), ((8, 12), 8.0)):  # a dolphin left of the centre, one right
        heat[0, iy, ix] = 0.9
        heat[0, iy, ix + 1] = 0.5  # a shoulder, not a peak
        regression[0, :, iy, ix] = (0.5, 0.5, np.log(distance))
    maxima = local_maxima(heat)
    assert maxima[0, 8, 3] and maxima[0, 8, 12] and not maxima[0, 8, 4] and not maxima[0, 8, 13]
    (peaks,) = read_peaks(heat, regression, 0.3, grid * stride, stride)
    assert len(peaks) == 2 and peaks.distance == pytest.approx(
        [5.0, 8.0]
    )  # the flat zeros are maxima too, below the threshold
    assert peaks.azimuth[0] > 0 > peaks.azimuth[1]  # + = left
    frames = [np.zeros((64, 64, 3), np.uint8), np.ones((64, 64, 3), np.uint8)]
    shown = {0: (np.zeros_like(heat), regression), 1: (heat, regression)}
    reader = TargetReader(lambda batch: shown[int(batch[0, 0, 0, 0])], 0.3, stride, grid * stride)
    assert reader.read(frames[0]) == UNSEEN
    near = reader.read(frames[1])
    assert near == pytest.approx((5.0, peaks.azimuth[0]))  # the nearer to the centre
    reader.reset(engage_deg=peaks.azimuth[1])
    assert reader.read(frames[1]) == pytest.approx((8.0, peaks.azimuth[1]))


def test_a_weak_stray_peak_at_the_centre_does_not_win_the_engagement() -> None:
    scores = np.array([0.35, 0.9, 0.8])  # a faint peak dead ahead, two dolphins seen plainly off the axis
    detections = Detections(scores, np.array([0.5, 25.0, -15.0]), np.zeros(3), np.array([6.0, 5.0, 7.0]))
    _, readings = run(PodTracker(), [detections])
    assert readings[0] == pytest.approx((7.0, -15.0))  # the strong peak nearest the centre


def test_no_dolphin_no_target_until_one_is_seen() -> None:
    state, readings = run(PodTracker(), [frame(), frame(), frame((5.0, 6.0))])
    assert readings[:2] == [None, None]
    assert readings[2] == pytest.approx((6.0, 5.0))


def test_a_companion_passing_in_front_does_not_take_the_target_over() -> None:
    """The companion (3 m) sweeps from 15 deg across the target (6 m, fixed at 0 deg) to -15 deg; while it covers
    the target only the companion is detected. Afterwards the target is the far dolphin at 0 deg again."""
    frames = []
    for step in range(61):
        companion = 15.0 - 0.5 * step
        covered = abs(companion) < 8.0
        frames.append(frame((companion, 3.0)) if covered else frame((0.0, 6.0), (companion, 3.0)))
    tracker = PodTracker()
    state, readings = run(tracker, frames)
    distance, azimuth = readings[-1]
    assert distance == pytest.approx(6.0, rel=0.05)
    assert azimuth == pytest.approx(0.0, abs=1.0)
    behind_steps = [i for i, f in enumerate(frames) if len(f) == 1]
    assert all(abs(readings[i][1]) < 9.0 for i in behind_steps)  # held within the one in front's disc
    assert all(readings[i][0] == pytest.approx(6.0, rel=0.05) for i in behind_steps)  # its distance kept


def target_track(state: np.ndarray) -> np.ndarray:
    tracks = state.reshape(MAX_TRACKS, len(FIELDS))
    return tracks[tracks[:, TARGET] > 0][0]


def test_the_target_behind_is_marked_and_released() -> None:
    tracker = PodTracker()
    state, _ = run(tracker, [frame((0.0, 6.0), (10.0, 3.0)), frame((0.0, 6.0), (5.0, 3.0)), frame((1.0, 3.0))])
    assert target_track(state)[BEHIND] == 1.0
    state, reading = tracker.update(state, frame((0.0, 6.0), (-4.0, 3.0)))
    assert target_track(state)[BEHIND] == 0.0
    assert reading == pytest.approx((6.0, 0.0), abs=0.3)


def test_a_moving_target_is_followed_through_missed_frames() -> None:
    """A target sweeping at 1 deg a frame, unseen for 5 frames, is found where it went, not a still companion."""
    frames = [frame((float(step), 6.0), (30.0, 6.0)) for step in range(20)]
    frames += [frame((30.0, 6.0)) for _ in range(5)]
    frames += [frame((25.0, 6.0), (30.0, 6.0))]
    _, readings = run(PodTracker(), frames)
    assert readings[-1][1] == pytest.approx(25.0, abs=1.5)


def test_a_target_lost_behind_no_one_is_given_up_for_the_likeliest_seen() -> None:
    """Unseen for longer than reacquire_after frames with nothing in front of it, the target passes to the dolphin
    seen nearest where it was, not to the one nearest the image centre."""
    tracker = PodTracker()
    lost = [frame((10.0, 6.0))] + [frame((-30.0, 3.0), (40.0, 9.0))] * (tracker.params.reacquire_after + 2)
    _, readings = run(tracker, lost)
    assert readings[tracker.params.reacquire_after - 5] == pytest.approx((6.0, 10.0))  # still waiting for it
    assert readings[-1] == pytest.approx((9.0, 40.0), abs=0.5)


def looking(look: float, *dolphins: tuple[float, float]) -> Detections:
    """Detections of dolphins that all look ``look`` grey levels lighter than the water."""
    plain = frame(*dolphins)
    return Detections(plain.score, plain.azimuth, plain.elevation, plain.distance, np.full(len(plain), look))


def test_a_look_alike_in_the_targets_place_is_told_apart_by_its_look() -> None:
    """The target (40 grey levels above the water) is learnt over 20 frames, then unseen while a paler companion
    (90) swims in where it was; the look keeps the target's track off it, so when the target shows again beside
    the companion it is the target that is read. Without the cue (look_sigma 0) the companion takes the track."""
    frames = [looking(40.0, (0.0, 6.0)) for _ in range(20)]
    frames += [looking(90.0, (0.5 * step, 6.3)) for step in range(10)]  # the companion alone, the target unseen
    frames += [Detections(np.ones(2), np.array([0.0, 6.0]), np.zeros(2), np.array([6.0, 6.3]), np.array([40.0, 90.0]))]
    state, readings = run(PodTracker(), frames)
    assert target_track(state)[LOOK] == pytest.approx(40.0) and target_track(state)[LOOK_READS] == 21
    assert readings[-1] == pytest.approx((6.0, 0.0), abs=0.3)
    _, blind = run(PodTracker(TrackerParams(look_sigma=0.0)), frames)
    assert blind[-1][1] == pytest.approx(6.0, abs=1.0)  # the companion, now at 6 deg


def test_a_look_is_the_animals_grey_above_the_water_even_a_pixel_off() -> None:
    """pixel_looks: a 3x3 dolphin of grey 130 in water of grey 50 reads 80 at its centre and a pixel off it (the
    lightest pixels of the window), and a darker one (grey 90) half as much."""
    image = np.full((64, 64, 3), 50, np.uint8)
    image[30:33, 10:13] = 130
    image[40:43, 50:53] = 90
    looks = pixel_looks(image, np.array([11.0, 12.4, 51.0]), np.array([31.0, 32.0, 41.0]))
    assert looks == pytest.approx([80.0, 80.0, 40.0])
    heat = np.zeros((1, 16, 16), np.float32)
    heat[0, 7, 2] = 0.9
    regression = np.zeros((1, 3, 16, 16), np.float32)
    regression[0, :, 7, 2] = (0.75, 0.75, np.log(5.0))  # the peak's centre at pixel (11, 31)
    (peaks,) = read_peaks(heat, regression, 0.3, 64, 4, image[None])
    assert peaks.look == pytest.approx([80.0])
    (unread,) = read_peaks(heat, regression, 0.3, 64, 4)
    assert np.isnan(unread.look).all()
