"""`swimm pilot`: fly ArduSub from a video stream with an exported policy.

    swimm pilot --policy runs/export/policy.onnx --source rtp://@:5600 --mavlink udpin:0.0.0.0:14550
    swimm pilot --policy policy.onnx --source dive.mp4 --dry-run          # compute and log, send nothing

A reader thread keeps the newest frame of the source; the control loop runs at the policy's rate: each new frame
(cropped and resized as the sim's camera sees, pilot_service.frames) gives an action, limited on every axis and
sent as MANUAL_CONTROL (pilot_service.vehicle). Safety: nothing is armed unless ``--arm``; a watchdog sends
neutral controls, and says so, while no frame has come for ``--frame-timeout-s`` (the policy's history starts
afresh when frames return); Ctrl-C, the end of a file and any error leave the vehicle with neutral controls.
Every control sent (or, with ``--dry-run``, computed) is appended to ``<out>/controls.csv`` as it happens, and
(``--record``, on by default) the session goes to ``<out>/session.mcap`` as `swimm record` writes a sim's: each
frame the policy saw as a ``foxglove.CompressedImage`` on ``pilot/camera``, each control on ``pilot/controls``.
"""

from __future__ import annotations

import csv
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from pilot_service.frames import FrameSource, SourceError, as_sim_frame, box_azimuth_deg
from pilot_service.policy import OnnxPolicy
from services.geometry import ALPHA_DEG
from services.keys import check_chunk
from services.lifecycle import stop_on_signals
from services.record import McapRecorder
from services.settings import FilePath, ZenohSettings

log = logging.getLogger(__name__)

CONTROL_FIELDS = ("time_s", "frame", "surge", "heave", "yaw", "neutral", "sent")
SESSION_FILE = "session.mcap"
SESSION_NAMESPACE = "pilot"  # the recording's metadata: it holds no wire samples for `swimm replay` to publish
CAMERA_TOPIC, CONTROLS_TOPIC = "pilot/camera", "pilot/controls"
#: One control tick, as session.mcap's JSON schema gives it to a viewer.
CONTROL_SCHEMA = {
    "title": "swimm.PilotControl",
    "type": "object",
    "properties": {
        "time_s": {"type": "number"},
        "frame": {"type": "integer"},
        "surge": {"type": "number"},
        "heave": {"type": "number"},
        "yaw": {"type": "number"},
        "neutral": {"type": "boolean"},
        "sent": {"type": "string"},
    },
}


@dataclass
class PilotSettings:
    policy: str = "runs/export/policy.onnx"  # the ONNX file `swimm export` wrote
    source: FilePath = "rtp://@:5600"  # a video file, a camera number, or a stream (the BlueROV2's: rtp://@:5600)
    camera_hfov_deg: float = 80.0  # the real camera's horizontal field of view (the BlueROV2 low-light camera's)
    mavlink: str = "udpin:0.0.0.0:14550"  # the vehicle's MAVLink endpoint (BlueOS sends to the GCS on UDP 14550)
    source_system: int = 255  # our MAVLink system id: ArduSub takes control from its SYSID_MYGCS (255)
    dive_mode: Literal["ALT_HOLD", "STABILIZE", "MANUAL"] = "ALT_HOLD"  # the ArduSub flight mode set at start
    arm: bool = False  # arm the vehicle at start; never without this flag
    dry_run: bool = False  # compute and log every action, connect to nothing and send nothing
    rate_hz: float = 0.0  # MANUAL_CONTROL per second; 0 = the policy's control rate
    frame_timeout_s: float = 0.5  # no new frame for this long: neutral controls until frames return
    max_surge: float = 0.5  # limit on |surge| sent, as a share of full
    max_yaw: float = 0.5  # limit on |yaw| sent, as a share of full
    max_heave: float = 0.5  # limit on |heave| sent by a policy that drives heave (the 3d task), as a share of full
    duration_s: float = 0.0  # stop after this many seconds; 0 = until the source ends or Ctrl-C
    heartbeat_timeout_s: float = 10.0  # how long to wait for the vehicle's first HEARTBEAT
    stream_timeout_s: float = 5.0  # a stream silent this long has stopped: the pilot ends, in neutral, saying so
    first_frame_timeout_s: float = 60.0  # a stream may start after the pilot: it waits this long for a first frame
    threads: int = 1  # onnxruntime threads
    # X Y W H in the source's pixels: the dolphin to follow, for a policy on a tracking CMVAE; empty: the one the
    # camera is centred on when the pilot starts (the rule the sim's pods train with)
    target_box: list[int] = field(default_factory=list)
    record: bool = True  # keep the session in <out>/session.mcap: every frame the policy saw, every control
    publish: bool = False  # also publish those frames into the namespace (--connect, --namespace) as a sim would
    publish_env: str = "pilot"  # the eval-channel env id the published frames go out as
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})  # where --publish goes
    out: str = ""  # the run folder (controls.csv, session.mcap); default runs/pilot-<UTC time>

    def check(self) -> None:
        if not all(0 < limit <= 1 for limit in (self.max_surge, self.max_yaw, self.max_heave)):
            raise ValueError(
                f"--max-surge, --max-yaw and --max-heave must be in (0, 1], got {self.max_surge}, {self.max_yaw}, "
                f"{self.max_heave}"
            )
        if self.rate_hz < 0 or self.frame_timeout_s <= 0 or self.duration_s < 0 or self.first_frame_timeout_s < 0:
            raise ValueError(
                "--rate-hz, --duration-s and --first-frame-timeout-s must be >= 0 and --frame-timeout-s > 0"
            )
        check_chunk(self.publish_env, "--publish-env")
        if self.target_box and (len(self.target_box) != 4 or min(self.target_box) < 0 or min(self.target_box[2:]) < 1):
            raise ValueError(f"--target-box takes X Y W H, a box of at least one pixel inside the frame, got "
                             f"{self.target_box}")  # fmt: skip


def target_azimuth_deg(settings: PilotSettings, frame: np.ndarray) -> float:
    """The azimuth of ``--target-box``'s centre in the first frame; a box outside the frame or outside the part of it
    the policy sees is refused by name."""
    x, y, w, h = settings.target_box
    height, width = frame.shape[:2]
    if x + w > width or y + h > height:
        raise ValueError(f"--target-box {settings.target_box} reaches past the {width} x {height} frame")
    azimuth = box_azimuth_deg((x, y, w, h), width, settings.camera_hfov_deg)
    if abs(azimuth) > ALPHA_DEG:
        raise ValueError(f"--target-box {settings.target_box} is centred {azimuth:+.1f} deg off the axis, outside the "
                         f"+-{ALPHA_DEG:.2f} deg the policy sees")  # fmt: skip
    return azimuth


class LatestFrame:
    """The newest frame a reader thread has taken from the source, with when it came; ``ended`` once the source
    gave no more."""

    def __init__(self, source: FrameSource) -> None:
        self.source = source
        self.frame: np.ndarray | None = None
        self.number = 0
        self.at = 0.0
        self.ended = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, name="frames", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        period, due = self.source.frame_period_s, time.monotonic()
        while (frame := self.source.read()) is not None:
            if period:  # a file plays at its own frame rate, as a camera would give it
                due += period
                time.sleep(max(0.0, due - time.monotonic()))
            with self._lock:
                self.frame, self.number, self.at = frame, self.number + 1, time.monotonic()
        self.ended.set()

    def get(self) -> tuple[np.ndarray | None, int, float]:
        with self._lock:
            return self.frame, self.number, self.at


class ControlLog:
    """controls.csv, one row per control tick, flushed as written: a crash keeps every row before it; with
    ``record``, also session.mcap, the frames the policy acted on beside the controls, for a viewer to replay."""

    def __init__(self, folder: Path, record: bool) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.path = folder / "controls.csv"
        self._file = self.path.open("w", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=CONTROL_FIELDS)
        self._writer.writeheader()
        self.session: McapRecorder | None = None
        if record:
            self.session = McapRecorder(folder / SESSION_FILE, SESSION_NAMESPACE, images=False)
            self._control_schema = self.session.schema("swimm.PilotControl", CONTROL_SCHEMA)

    def frame(self, frame: np.ndarray, number: int) -> None:
        """The frame (as the policy saw it) that the next controls act on."""
        if self.session is not None:
            now_ns = time.time_ns()
            self.session.write_image(CAMERA_TOPIC, frame, now_ns, f"frame {number}", now_ns)

    def write(self, **row: object) -> None:
        self._writer.writerow(row)
        self._file.flush()
        if self.session is not None:
            self.session.write_json(CONTROLS_TOPIC, row, time.time_ns(), self._control_schema)

    def close(self) -> None:
        self._file.close()
        if self.session is not None:
            self.session.close()


NEUTRAL = {"surge": 0.0, "heave": 0.0, "yaw": 0.0}


def limited(action: np.ndarray, names: list[str], settings: PilotSettings) -> dict[str, float]:
    """Surge, heave and yaw within the axis limits; heave 0 (depth held) from a policy that does not drive it."""
    limits = {"surge": settings.max_surge, "heave": settings.max_heave, "yaw": settings.max_yaw}
    commands = zip(names, action, strict=True)
    return NEUTRAL | {name: float(np.clip(value, -limits[name], limits[name])) for name, value in commands}


def check_dive_mode(action_names: list[str], dive_mode: str) -> None:
    """Refuse to fly a policy that drives heave in a mode that reads the heave stick as thrust, not climb rate."""
    if "heave" in action_names and dive_mode != "ALT_HOLD":
        raise ValueError(
            f"the policy drives heave as a climb rate, which ArduSub reads so only in ALT_HOLD, not {dive_mode}: "
            "fly it with --dive-mode ALT_HOLD"
        )


def flyable_policy(settings: PilotSettings) -> OnnxPolicy:
    """The settings checked and the policy loaded, refused where it cannot fly them (its actions, a target box)."""
    settings.check()
    policy = OnnxPolicy(settings.policy, settings.threads)
    check_dive_mode(policy.action_names, settings.dive_mode)
    if settings.target_box and not policy.tracks:
        raise ValueError(f"--target-box points a target out to a policy on a tracking CMVAE or the pod detector; "
                         f"{settings.policy} reads no prior: it follows the dolphin centred in view")  # fmt: skip
    return policy


def check(settings: PilotSettings) -> None:
    """`swimm pilot`'s check: before any source or vehicle is opened."""
    flyable_policy(settings)


def fly(settings: PilotSettings, stop: threading.Event) -> Path:
    """The control loop until ``stop``, the duration, or the end of a file; returns the controls CSV's path."""
    policy = flyable_policy(settings)
    rate = settings.rate_hz or policy.control_rate_hz
    vehicle = None
    if not settings.dry_run:
        from pilot_service.vehicle import Vehicle  # pymavlink only where a vehicle is flown

        vehicle = Vehicle(settings.mavlink, settings.source_system, settings.heartbeat_timeout_s)
    source = FrameSource(settings.source, settings.stream_timeout_s, settings.first_frame_timeout_s)
    folder = Path(settings.out or f"runs/pilot-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}")
    controls = ControlLog(folder, settings.record)
    publisher = None
    if settings.publish:
        from pilot_service.publish import FramePublisher  # Zenoh only where frames are published

        publisher = FramePublisher(settings.zenoh, settings.publish_env)
    latest = LatestFrame(source)
    started = time.monotonic()
    used, stalled, command = 0, False, NEUTRAL
    try:
        if vehicle is not None:
            vehicle.set_mode(settings.dive_mode)
            if settings.arm:
                vehicle.arm()
        target = " (dry run: nothing is sent)" if vehicle is None else f" to {settings.mavlink}"
        log.info("piloting from %s at %g Hz%s; controls in %s", settings.source, rate, target, controls.path)
        tick = started
        while not stop.is_set():
            now = time.monotonic()
            if settings.duration_s and now - started >= settings.duration_s:
                break
            frame, number, at = latest.get()
            fresh = frame is not None and now - at <= settings.frame_timeout_s
            if not fresh and latest.ended.is_set():
                if not number:
                    raise SourceError(f"the video source {settings.source!r} opened but gave no frame")
                if not source.is_file:
                    raise SourceError(f"the stream {settings.source!r} stopped giving frames after {number}")
                log.info("the source ended after %d frames", number)
                break
            if fresh and number != used:
                if stalled:
                    log.warning("frames are back (frame %d): the policy starts afresh on the dolphin in the centre",
                                number)  # fmt: skip
                    policy.reset()
                elif not used and settings.target_box:
                    azimuth = target_azimuth_deg(settings, frame)
                    policy.reset(azimuth)
                    log.info("following the dolphin in %s, %+.1f deg off the axis", settings.target_box, azimuth)
                stalled, used = False, number
                seen = as_sim_frame(frame, settings.camera_hfov_deg, policy.image_size)
                controls.frame(seen, number)
                if publisher is not None:
                    publisher.publish(seen, number)
                command = limited(policy.act(seen), policy.action_names, settings)
            elif not fresh:
                if not stalled and number:  # before the first frame there is nothing to have stalled
                    log.warning("no frame for %.2f s: neutral controls until frames return", now - at)
                stalled, command = number > 0, NEUTRAL
            sent = vehicle.send_control(**command) if vehicle is not None else None
            controls.write(time_s=round(now - started, 4), frame=used, **command, neutral=not fresh,
                           sent=" ".join(map(str, sent)) if sent else "")  # fmt: skip
            tick += 1.0 / rate
            stop.wait(max(0.0, tick - time.monotonic()))
    finally:
        if vehicle is not None:
            vehicle.send_control(0.0, 0.0)  # whatever ended the loop, the vehicle is left in neutral
            vehicle.close()
        controls.close()
        source.close()
        if publisher is not None:
            publisher.close()
    log.info("stopped after %.1f s; %d frames used; controls in %s", time.monotonic() - started, used, controls.path)
    return controls.path


def run(settings: PilotSettings) -> int:
    stop = threading.Event()
    with stop_on_signals(stop, "sending neutral controls and stopping"):
        try:
            fly(settings, stop)
        except SourceError as exc:
            log.error("%s", exc)
            return 1
    return 0
