"""`swimm encoder`: observations in, latents out, batched across environments.

Routing: the learner picks one live encoder per group of envs (rendezvous
hashing over the encoders' liveliness tokens) and the sim publishes the
group's observations, one message, on ``<ns>/<channel>/<group>/obs/<encoder
id>``. This encoder subscribes only to its own id, so each frame crosses the
network once and is encoded once. When an encoder dies its token goes; the
learner's next retry routes to a live one (docs/encoder_service.md gives the
bound).

Batching (:class:`LatentBatcher`): the Zenoh callback only queues raw
bytes; one worker thread takes the first waiting message, gathers more
until ``max_batch`` messages or ``max_wait_ms`` have passed, encodes all
their frames in one forward pass and answers each message with one message
of latents, telemetry passed through, an env the sim refused passed on as
its error item. A frame that cannot be decoded or has the wrong shape or
dtype becomes an error item with the reason, logged and counted; a message
that cannot be read at all is logged and counted (the learner's timeout
names the step). The service keeps serving.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections import deque
from contextlib import ExitStack
from dataclasses import dataclass, field

import numpy as np
import zenoh

from encoder_service import Engine
from encoder_service.inference import DEFAULT_CHECKPOINT, check_encoder_file, check_engine, open_encoder
from encoder_service.model import resolve_device
from services.keys import Keys
from services.lifecycle import Service, serve_until_signalled
from services.messages import IMAGE_SHAPE, BadMessage, BatchItem, BatchMsg, LatentMsg, ObservationMsg, Prior
from services.metrics import Metrics, MetricsPublisher
from services.presence import announce, declare_about
from services.results import file_sha256
from services.session import open_session
from services.settings import FilePath, NonNegFloat, NonNegInt, PosFloat, PosInt, ZenohSettings

log = logging.getLogger(__name__)


@dataclass
class EncoderSettings:
    zenoh: ZenohSettings = field(default_factory=ZenohSettings, metadata={"flatten": True})
    checkpoint: FilePath = ""  # a CMVAE or a pod detector checkpoint; default: the shipped CMVAE
    max_batch: PosInt = 32  # frames per forward pass
    max_wait_ms: NonNegFloat = 0.0  # how long the first frame of a batch waits for company; 0 = take what is queued
    device: str = "cpu"
    threads: NonNegInt = 0  # torch threads; 0 = torch's default (onnx: one)
    engine: Engine = "torch"  # torch (a frozen TorchScript trace) | onnx (onnxruntime, CPU; faster, batch-invariant)
    ident: str = ""  # this encoder's id in routing keys and liveliness; default enc-<pid>
    metrics_period_s: PosFloat = 2.0  # how often counters go out on <ns>/metrics/encoder/<id>


@dataclass
class _Frame:
    key: str
    payload: bytes
    received_at: float


class LatentBatcher:
    """Gathers frames into batches: the first waits at most ``max_wait_ms`` for up to ``max_batch - 1`` more.

    Frames already queued join at once, so under load batches fill without
    waiting; the wait only matters when frames trickle in.
    """

    def __init__(self, max_batch: int, max_wait_ms: float) -> None:
        if max_batch < 1 or max_wait_ms < 0:
            raise ValueError(f"max_batch must be >= 1 and max_wait_ms >= 0 (got {max_batch}, {max_wait_ms})")
        self.max_batch = max_batch
        self.max_wait_s = max_wait_ms / 1e3
        self.inbox: queue.Queue[_Frame | None] = queue.Queue()

    def put(self, frame: _Frame) -> None:
        self.inbox.put(frame)

    def next_batch(self, idle_timeout_s: float = 0.5) -> list[_Frame] | None:
        """A batch, [] when idle for ``idle_timeout_s``, or None once closed."""
        try:
            first = self.inbox.get(timeout=idle_timeout_s)
        except queue.Empty:
            return []
        if first is None:
            return None
        batch = [first]
        deadline = time.perf_counter() + self.max_wait_s
        while len(batch) < self.max_batch:
            left = deadline - time.perf_counter()
            try:
                item = self.inbox.get(timeout=left) if left > 0 else self.inbox.get_nowait()
            except queue.Empty:
                break
            if item is None:
                self.inbox.put(None)  # finish this batch, stop on the next call
                break
            batch.append(item)
        return batch

    def close(self) -> None:
        """Stop after the frames already queued have been served (a drain, not a drop)."""
        self.inbox.put(None)


class EncoderMetrics(Metrics):
    """The shared counters and latency percentiles, plus batch sizes and throughput over a recent window."""

    def __init__(self, window_s: float = 10.0) -> None:
        super().__init__()
        self._window_s = window_s
        self._batches: deque[tuple[float, int]] = deque()  # (time, size), the last window_s seconds

    def record_batch(self, size: int) -> None:
        self.count("batches")
        self.count("images", size)
        now = time.monotonic()
        with self._lock:
            self._batches.append((now, size))
            while self._batches and self._batches[0][0] < now - self._window_s:
                self._batches.popleft()

    def snapshot(self) -> dict[str, float]:
        snap = super().snapshot()
        now = time.monotonic()
        with self._lock:
            sizes = [size for at, size in self._batches if at >= now - self._window_s]
        snap["batch_size_mean"] = float(np.mean(sizes)) if sizes else 0.0
        snap["batch_size_max"] = float(max(sizes, default=0))
        snap["images_per_s"] = sum(sizes) / self._window_s
        return snap


@dataclass
class _Group:
    """A group's observations (sim -> here) on their way to being one message of latents (here -> learner)."""

    frame: _Frame
    channel: str
    batch: BatchMsg
    observations: list[ObservationMsg | str]  # the observation, or why its item carries none (passed on as its error)


class EncoderService(Service):
    def __init__(self, settings: EncoderSettings) -> None:
        self.settings = settings
        self.keys = Keys(settings.zenoh.namespace)
        self.ident = settings.ident or f"enc-{os.getpid()}"
        self.encoder = open_encoder(
            settings.checkpoint or DEFAULT_CHECKPOINT, settings.device, settings.threads or None, settings.engine
        )
        # A tracking encoder's prior for one frame, flattened as it travels; a frame without one (a new episode's
        # first) starts from zeros: the image centre, or for the pod tracker no track yet.
        self._prior_size = int(np.prod(self.encoder.prior_shape)) if self.encoder.tracks else 0
        self.batcher = LatentBatcher(settings.max_batch, settings.max_wait_ms)
        self.metrics = EncoderMetrics()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._worker = threading.Thread(target=self._work, name="encoder-worker", daemon=True)

    @property
    def inbox_key(self) -> str:
        return self.keys.encoder_inbox(self.ident)

    def start(self) -> None:
        # Closed in reverse: the token goes first, so learners route elsewhere; the worker finishes its batches
        # before the publishers it answers on go.
        own = self.resources.enter_context
        self.session = own(open_session(self.settings.zenoh, role="encoder"))
        self._declared_by_worker = own(ExitStack())
        self._worker.start()
        self.resources.callback(self._worker.join, timeout=10)
        self.resources.callback(self.batcher.close)
        own(self.session.declare_subscriber(self.inbox_key, self._on_frame))
        own(MetricsPublisher(self.session, self.keys, "encoder", self.ident, self.metrics,
                             self.settings.metrics_period_s))  # fmt: skip
        # Learners and evaluations check that this is the CMVAE their policy was trained with.
        about = {"checkpoint": str(self.encoder.checkpoint), "sha256": file_sha256(self.encoder.checkpoint)}
        own(declare_about(self.session, self.keys, "encoder", self.ident, about))
        # Announce last: a learner routes here only once this encoder can hear it.
        own(announce(self.session, self.keys, "encoder", self.ident))
        log.info(
            "encoder %s serving %s with %s (max batch %d, max wait %.1f ms)",
            self.ident,
            self.inbox_key,
            self.encoder.checkpoint,
            self.settings.max_batch,
            self.settings.max_wait_ms,
        )

    def _on_frame(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: copy and queue only; decoding and torch run on the worker."""
        self.batcher.put(_Frame(str(sample.key_expr), sample.payload.to_bytes(), time.perf_counter()))

    def _work(self) -> None:
        while (batch := self.batcher.next_batch()) is not None:
            if not batch:
                continue
            try:
                self._encode(batch)
            except Exception:  # a bug or a torch failure on one batch must not end the service
                self.metrics.count("errors_internal")
                log.exception("could not encode a batch of %d frames", len(batch))

    def _decode(self, frame: _Frame) -> _Group | None:
        try:
            channel, _ = self.keys.parse_step_key(frame.key)
            batch = BatchMsg.decode(frame.payload)
        except (BadMessage, ValueError) as exc:  # no env to answer: the learner's retry will name the step
            self.metrics.count("errors_refused")
            log.warning("refused a group of frames on %s: %s", frame.key, exc)
            return None
        observations: list[ObservationMsg | str] = []
        for item in batch.items:
            if item.error:  # the sim's refusal, passed on as it came
                observations.append(item.error)
                continue
            try:
                observations.append(self._observation(item))
            except BadMessage as exc:
                self.metrics.count("errors_refused")
                log.warning("refused the frame of %s/%s in group %s: %s", channel, item.env, batch.group, exc)
                observations.append(f"encoder {self.ident} refused the frame: {exc}")
        return _Group(frame, channel, batch, observations)

    def _observation(self, item: BatchItem) -> ObservationMsg:
        obs = ObservationMsg.from_item(item, IMAGE_SHAPE)
        if self._prior_size and obs.prior is not None and len(obs.prior) != self._prior_size:
            raise BadMessage(f"prior of {len(obs.prior)} numbers; {self.encoder.checkpoint} reads {self._prior_size}")
        return obs

    def _encode(self, frames: list[_Frame]) -> None:
        """One forward pass for every frame of every group in ``frames``, then one message of latents per group."""
        groups = [group for frame in frames if (group := self._decode(frame)) is not None]
        observed = [obs for group in groups for obs in group.observations if isinstance(obs, ObservationMsg)]
        if observed:
            images = np.stack([obs.image for obs in observed])
            if self.encoder.tracks:
                priors = np.zeros((len(observed), self._prior_size), np.float32)
                for row, obs in enumerate(observed):
                    priors[row] = obs.prior or 0.0
                shaped = priors.reshape(len(observed), *self.encoder.prior_shape)
                mu, logvar, states = self.encoder.track(images, shaped)
                next_priors = [tuple(state) for state in states.reshape(len(observed), -1).tolist()]
            else:
                (mu, logvar), next_priors = self.encoder.encode(images), [None] * len(observed)
            self.metrics.record_batch(len(observed))
        rows = iter(range(len(observed)))
        for group in groups:
            items = []
            for source, obs in zip(group.batch.items, group.observations, strict=True):
                if isinstance(obs, str):
                    items.append(BatchItem(source.env, source.ep, source.seq, error=obs))
                    continue
                row = next(rows)
                items.append(BatchItem.of(obs.env, self._latent(obs, mu[row], logvar[row], next_priors[row])))
            reply = BatchMsg(group.batch.group, self.ident, tuple(items), group.batch.to)
            self._publisher(self.keys.latent(group.channel, group.batch.group)).put(reply.encode())
            self.metrics.observe_ms("latency", (time.perf_counter() - group.frame.received_at) * 1e3)

    def _latent(self, obs: ObservationMsg, mu: np.ndarray, logvar: np.ndarray, next_prior: Prior | None) -> LatentMsg:
        return LatentMsg(
            env=obs.env,
            ep=obs.ep,
            seq=obs.seq,
            telemetry=obs.telemetry,
            mu=tuple(mu.tolist()),
            logvar=tuple(logvar.tolist()),
            encoder=self.ident,
            next_prior=next_prior,
        )

    def _publisher(self, key: str) -> zenoh.Publisher:
        if key not in self._publishers:
            publisher = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            self._publishers[key] = self._declared_by_worker.enter_context(publisher)
        return self._publishers[key]

    def close(self) -> None:
        super().close()
        log.info("encoder %s stopped: %s", self.ident, self.metrics.snapshot())


def check(settings: EncoderSettings) -> None:
    """`swimm encoder`'s check: the engine on its device and the checkpoint, before a model loads or a session
    opens."""
    check_engine(settings.engine, settings.device)
    resolve_device(settings.device)
    check_encoder_file(settings.checkpoint or DEFAULT_CHECKPOINT, settings.engine, settings.device)


def run(settings: EncoderSettings) -> None:
    serve_until_signalled(EncoderService(settings))
