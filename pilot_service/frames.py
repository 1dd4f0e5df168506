"""Frames from a real camera, seen as the sim's camera sees them.

A source is a video file, a local camera device (its number), or a network stream: ``rtp://@:5600`` is the
BlueROV2's H.264 RTP stream on UDP port 5600 (read through an SDP description written for it, FFmpeg's way of
receiving raw RTP), and any other URL FFmpeg opens (``udp://``, ``rtsp://``, ...) is passed as it is.
Each frame is cropped to the sim camera's field of view (79.95 x 64.4 degrees, the IMX322's) from the real
camera's horizontal field of view, then resized to the policy's input: the sim renders that view into a square.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import time
from pathlib import Path
from urllib.parse import urlparse

import cv2
import numpy as np

from services.geometry import HFOV_DEG, VFOV_DEG

log = logging.getLogger(__name__)

RTP_SDP = """v=0
o=- 0 0 IN IP4 127.0.0.1
s=swimm pilot
c=IN IP4 {host}
t=0 0
m=video {port} RTP/AVP 96
a=rtpmap:96 H264/90000
"""


class SourceError(RuntimeError):
    """A video source that cannot be opened or stopped giving frames; the message names it."""


def crop_box(width: int, height: int, camera_hfov_deg: float) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the centred region of a ``width`` x ``height`` frame that spans the sim camera's view, for a
    pinhole camera of horizontal field ``camera_hfov_deg`` with square pixels (the whole frame if it sees less)."""
    half_width = math.tan(math.radians(camera_hfov_deg) / 2)
    half_height = half_width * height / width
    w = min(1.0, math.tan(math.radians(HFOV_DEG) / 2) / half_width) * width
    h = min(1.0, math.tan(math.radians(VFOV_DEG) / 2) / half_height) * height
    return round((width - w) / 2), round((height - h) / 2), round(w), round(h)


def box_azimuth_deg(box: tuple[float, float, float, float], width: int, camera_hfov_deg: float) -> float:
    """The azimuth (degrees, + = left, as the sim's) of the centre of an (x, y, w, h) pixel box in a frame ``width``
    pixels wide, for a pinhole camera of horizontal field ``camera_hfov_deg``: where a tracking CMVAE's prior starts."""
    x, _, w, _ = box
    offset = (x + w / 2) / width * 2 - 1  # -1 at the left edge, +1 at the right
    return -math.degrees(math.atan(offset * math.tan(math.radians(camera_hfov_deg) / 2)))


def as_sim_frame(bgr: np.ndarray, camera_hfov_deg: float, size: int) -> np.ndarray:
    """An OpenCV BGR frame as the policy's input: the sim camera's view, ``size`` x ``size`` RGB uint8."""
    x, y, w, h = crop_box(bgr.shape[1], bgr.shape[0], camera_hfov_deg)
    view = cv2.resize(bgr[y : y + h, x : x + w], (size, size), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(view, cv2.COLOR_BGR2RGB)


class FrameSource:
    """Opens a source and reads frames from it; ``read`` returns None once the source has ended. A live source that
    has given no frame yet is opened again until ``first_frame_timeout_s`` has passed: a stream may start after the
    pilot, and FFmpeg cannot decode a stream it opened before the stream's first packets described it."""

    def __init__(self, source: str, read_timeout_s: float = 5.0, first_frame_timeout_s: float = 0.0) -> None:
        self.source = source
        self.is_file = Path(source).is_file()  # a file's end is the end of the flight; a stream's is an error
        self._sdp: Path | None = None
        self._read_timeout_s = read_timeout_s
        self._first_frame_deadline = time.monotonic() + first_frame_timeout_s
        self._seen_a_frame = False
        self._closed = False
        self.capture = self._open()
        if not self.capture.isOpened():
            self.close()
            raise SourceError(f"cannot open the video source {source!r} (a file, a camera number, or a stream URL "
                              "such as rtp://@:5600)")  # fmt: skip

    def _open(self) -> cv2.VideoCapture:
        if self.source.isdigit():
            return cv2.VideoCapture(int(self.source))
        # Bounded waits: a stream that stops makes read() fail instead of blocking for ever.
        timeouts = [
            cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
            10_000,
            cv2.CAP_PROP_READ_TIMEOUT_MSEC,
            int(self._read_timeout_s * 1000),
        ]
        target = str(self._sdp) if self._sdp is not None else self._ffmpeg_target(self.source)
        return cv2.VideoCapture(target, cv2.CAP_FFMPEG, timeouts)

    def _ffmpeg_target(self, source: str) -> str:
        url = urlparse(source)
        if url.scheme == "rtp":  # raw RTP: FFmpeg needs the stream's description
            host = url.hostname or "0.0.0.0"
            handle, name = tempfile.mkstemp(suffix=".sdp", prefix="swimm-pilot-")
            os.close(handle)
            self._sdp = Path(name)
            self._sdp.write_text(RTP_SDP.format(host=host, port=url.port or 5600))
            # Low latency: no input buffering, a short probe of the stream before the first frame.
            os.environ.setdefault("OPENCV_FFMPEG_CAPTURE_OPTIONS",
                                  "protocol_whitelist;file,udp,rtp|fflags;nobuffer|analyzeduration;500000")  # fmt: skip
            return str(self._sdp)
        if not url.scheme and not Path(source).is_file():
            raise SourceError(f"no video file at {source!r}")
        return source

    @property
    def frame_period_s(self) -> float:
        """A file's time between frames (its frame rate), so it plays as its camera filmed it; 0 for a live source,
        whose frames come when they come."""
        fps = self.capture.get(cv2.CAP_PROP_FPS) if self.is_file else 0.0
        return 1.0 / fps if fps > 0 else 0.0

    def read(self) -> np.ndarray | None:
        while True:
            ok, frame = self.capture.read()
            if ok:
                self._seen_a_frame = True
                return frame
            if self._seen_a_frame or self.is_file or self._closed or time.monotonic() >= self._first_frame_deadline:
                return None
            log.info("no frame from %s yet: opening it again to wait for the stream", self.source)
            self.capture.release()
            self.capture = self._open()

    def close(self) -> None:
        self._closed = True  # a reader thread waiting for a first frame stops opening the source again
        self.capture.release()
        if self._sdp is not None:
            self._sdp.unlink(missing_ok=True)
