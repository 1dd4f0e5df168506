"""What `swimm record` and `swimm replay` do: every sample of a namespace kept in an MCAP file, and published
back (their commands: swimm/record.py).

Zenoh keeps only the latest value of a key; a dive, a training run or an evaluation is worth keeping whole.
`swimm record` subscribes to ``<ns>/**`` and writes each sample to MCAP (the mcap library) on a channel named
after its key, with message encoding ``msgpack``: the bytes exactly as they went over the wire, the observations
with their frames, the latents, the actions, refusals and metrics. Each camera frame of an env's observation is
also written on ``<key>/image`` as a ``foxglove.CompressedImage`` (JSON encoding, PNG data), which Foxglove shows
as a video and Rerun's MCAP loader reads. The recorded namespace is in the file's ``swimm`` metadata record.

`swimm replay FILE` publishes the msgpack channels back into the same keys, at the recorded pace or as fast as
it can (``--speed full``), under the recorded namespace or another (``--namespace``): an encoder started there
answers replayed observations as it answered them live (a tracking one too: each observation carries its prior).
The bytes are the recorded ones, so a replayed episode is bit-exact. Control requests (claim, reset) are
request/reply, not samples: they are not in a recording, and an episode's start shows as its observation of step 0.
Liveliness tokens are not samples either.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import queue
import struct
import threading
import time
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zenoh
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import Writer

from services.messages import BadMessage, ObservationMsg, batch_messages
from services.session import open_session, wait_for_matching
from services.settings import ZenohSettings

log = logging.getLogger(__name__)

RAW_ENCODING = "msgpack"  # a channel whose messages are the wire's bytes: what replay publishes
IMAGE_TOPIC_SUFFIX = "/image"
METADATA_NAME = "swimm"
LISTENER_WAIT_S = 3.0  # how long replay waits for every key's listeners to be known before it publishes
#: Foxglove's CompressedImage as a JSON schema (bytes as base64 in JSON encoding).
COMPRESSED_IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}


@dataclass
class RecordSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    out: str = ""  # the MCAP file; default runs/record-<UTC time>.mcap
    duration_s: float = 0.0  # stop after this many seconds; 0 = until Ctrl-C or SIGTERM
    images: bool = True  # also write each env's frames as foxglove.CompressedImage for viewers

    def check(self) -> None:
        if self.duration_s < 0:
            raise ValueError(f"--duration-s must be >= 0 (0: until stopped), got {self.duration_s}")
        if self.images:
            try:
                import cv2  # noqa: F401  (PNG encoding of the frames)
            except ImportError:
                raise ValueError("--images needs OpenCV (pip install 'swimm[sim]'), or record --no-images") from None


@dataclass
class ReplaySettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    file: str = field(default="", metadata={"positional": True, "help": "an MCAP file written by `swimm record`"})
    speed: Literal["recorded", "full"] = "recorded"  # recorded: the recorded gaps between samples; full: none
    namespace_from_file: bool = True  # publish under the recorded namespace; --no-namespace-from-file: --namespace
    keys: str = "**"  # replay only the recorded keys this expression (under the namespace) matches, e.g. "*/*/obs/*"

    def check(self) -> None:
        if not self.file:
            raise ValueError("give the recording to replay: swimm replay FILE.mcap")
        if not Path(self.file).is_file():
            raise FileNotFoundError(f"no recording at {self.file}")
        recorded_namespace(self.file)  # a file that is no swimm recording
        try:
            zenoh.KeyExpr(f"swimm/{self.keys}")
        except zenoh.ZError as exc:
            reason = str(exc).split(" at /")[0]  # without the Rust source location
            raise ValueError(f"--keys {self.keys!r} is not a key expression: {reason}") from None


class McapRecorder:
    """Writes samples to one MCAP file from a single thread (the mcap writer is not thread-safe)."""

    def __init__(self, path: Path, namespace: str, images: bool) -> None:
        self._file = path.open("wb")
        self.writer = Writer(self._file)
        self.writer.start(profile="", library="swimm")
        self.writer.add_metadata(METADATA_NAME, {"namespace": namespace})
        self.images = images
        self._image_schema = self.schema("foxglove.CompressedImage", COMPRESSED_IMAGE_SCHEMA)
        self._channels: dict[str, int] = {}
        self.messages = 0

    def _channel(self, topic: str, encoding: str, schema: int = 0) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self.writer.register_channel(topic, encoding, schema)
        return channel

    @property
    def topics(self) -> int:
        return len(self._channels)

    def write(self, key: str, payload: bytes, received_ns: int) -> None:
        self.writer.add_message(self._channel(key, RAW_ENCODING), received_ns, payload, received_ns, self.messages)
        self.messages += 1
        if self.images and "/obs/" in key:
            self._write_image(key, payload, received_ns)

    def _write_image(self, key: str, payload: bytes, received_ns: int) -> None:
        try:
            frames = batch_messages(payload, ObservationMsg.from_item)
        except BadMessage:
            return  # not readable observations: kept raw above
        for env, msg in frames:  # a group's frames share its key's image channel, each named by its env
            if msg.image is not None:
                self.write_image(key + IMAGE_TOPIC_SUFFIX, msg.image, int(msg.sent_at * 1e9), env, received_ns)

    def write_image(self, topic: str, rgb: np.ndarray, stamp_ns: int, frame_id: str, log_ns: int) -> None:
        """An RGB frame on ``topic`` as a foxglove.CompressedImage (PNG, lossless)."""
        import cv2  # only where frames are recorded as images

        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if not ok:
            raise ValueError(f"OpenCV could not PNG-encode a {rgb.shape} frame for {topic}")
        sec, nsec = divmod(stamp_ns, 1_000_000_000)
        body = {"timestamp": {"sec": sec, "nsec": nsec}, "frame_id": frame_id, "format": "png",
                "data": base64.b64encode(png.tobytes()).decode()}  # fmt: skip
        self.write_json(topic, body, log_ns, self._image_schema)

    def write_json(self, topic: str, body: dict[str, Any], log_ns: int, schema: int = 0) -> None:
        """A JSON message on ``topic`` (``schema``: an id from :meth:`schema`; 0 = schemaless)."""
        channel = self._channel(topic, "json", schema)
        self.writer.add_message(channel, log_ns, json.dumps(body).encode(), log_ns, self.messages)
        self.messages += 1

    def schema(self, name: str, json_schema: dict[str, Any]) -> int:
        """Register a JSON schema, for viewers to read a topic's fields by."""
        return self.writer.register_schema(name, "jsonschema", json.dumps(json_schema).encode())

    def close(self) -> None:
        self.writer.finish()
        self._file.close()


def record(settings: RecordSettings, stop: threading.Event) -> dict[str, Any]:
    """Record until ``stop`` is set or the duration is up; returns what was written."""
    settings.check()
    out = Path(settings.out or f"runs/record-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}.mcap")
    out.parent.mkdir(parents=True, exist_ok=True)
    samples: queue.SimpleQueue[tuple[str, bytes, int]] = queue.SimpleQueue()
    namespace = settings.zenoh.namespace
    until = f" for {settings.duration_s:g} s" if settings.duration_s else " until stopped"
    with (
        open_session(settings.zenoh, role="recorder") as session,
        closing(McapRecorder(out, namespace, settings.images)) as recorder,
    ):
        log.info("recording %s/** to %s%s", namespace, out, until)
        started = time.monotonic()
        ends = started + settings.duration_s if settings.duration_s else math.inf
        try:
            with session.declare_subscriber(
                f"{namespace}/**",
                lambda sample: samples.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())),
            ):
                while not stop.is_set() and time.monotonic() < ends:
                    try:
                        recorder.write(*samples.get(timeout=0.1))
                    except queue.Empty:
                        continue
        finally:
            while not samples.empty():  # what arrived before the subscriber went
                recorder.write(*samples.get())
    summary = {"file": str(out), "messages": recorder.messages, "topics": recorder.topics,
               "seconds": round(time.monotonic() - started, 1), "namespace": namespace}  # fmt: skip
    log.info("recorded %d messages on %d topics in %.1f s to %s", summary["messages"], summary["topics"],
             summary["seconds"], out)  # fmt: skip
    return summary


def recorded_namespace(path: str | Path) -> str:
    """The namespace a recording was made in; a file that is not a swimm MCAP recording is refused by name."""
    try:
        with open(path, "rb") as handle:
            for record in make_reader(handle).iter_metadata():
                if record.name == METADATA_NAME:
                    return record.metadata["namespace"]
    except (McapError, OSError, struct.error) as exc:  # struct: a file too short for MCAP's header
        raise ValueError(f"{path} is not a readable MCAP recording: {exc}") from None
    raise ValueError(f"{path} has no swimm metadata: was it written by `swimm record`?")


def recorded_samples(path: str | Path) -> list[tuple[str, bytes, int]]:
    """(key, payload, log time ns) of every wire-format message of a recording, in log-time order."""
    with open(path, "rb") as handle:
        return [(channel.topic, message.data, message.log_time)
                for _, channel, message in make_reader(handle).iter_messages(log_time_order=True)
                if channel.message_encoding == RAW_ENCODING]  # fmt: skip


def replay(settings: ReplaySettings, stop: threading.Event) -> int:
    """Publish a recording's samples back; returns how many were published."""
    settings.check()
    source = recorded_namespace(settings.file)
    target = source if settings.namespace_from_file else settings.zenoh.namespace
    wanted = zenoh.KeyExpr(f"{source}/{settings.keys}")
    samples = [sample for sample in recorded_samples(settings.file) if wanted.intersects(zenoh.KeyExpr(sample[0]))]
    published = 0
    with open_session(settings.zenoh, role="replay") as session:
        publishers = {key: session.declare_publisher(target + key[len(source) :],
                                                     congestion_control=zenoh.CongestionControl.BLOCK)
                      for key in dict.fromkeys(sample[0] for sample in samples)}  # fmt: skip
        wait_for_matching(publishers.values(), LISTENER_WAIT_S)  # or the first samples reach nobody
        first_ns, started = (samples[0][2] if samples else 0), time.monotonic()
        for key, payload, log_ns in samples:
            if stop.is_set():
                break
            if settings.speed == "recorded":
                stop.wait(max(0.0, (log_ns - first_ns) / 1e9 - (time.monotonic() - started)))
            publishers[key].put(payload)
            published += 1
    log.info("replayed %d of %d samples from %s into %s", published, len(samples), settings.file, target)
    return published
