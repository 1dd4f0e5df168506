"""The sample dive video the pilot's docs fly: a film of the tracker that OpenCV reads back frame for frame."""

from __future__ import annotations

import cv2

from eval_service.sample_video import write_video


def test_the_sample_video_is_a_readable_film_of_the_dive(tmp_path) -> None:
    out = tmp_path / "dive.mp4"
    assert write_video(out, seconds=0.4, size=96, every=2, seed=9001) == 10
    capture = cv2.VideoCapture(str(out))
    assert capture.get(cv2.CAP_PROP_FPS) == 25 and capture.get(cv2.CAP_PROP_FRAME_COUNT) == 10
    ok, frame = capture.read()
    assert ok and frame.shape == (96, 96, 3) and frame.std() > 1  # a picture, not a blank
    capture.release()
