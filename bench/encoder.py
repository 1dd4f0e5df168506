"""Encoder benchmark: one `swimm encoder` process fed one environment at a time vs many at once.

Both halves run in one invocation against the same encoder process and
router, so the ratio isolates what batching across environments buys.
Every environment is lock-step, as a learner drives it: it sends a frame
and sends its next only once that frame's latent came back. With one
environment each forward pass holds one image; with ``envs`` environments
the frames that queue up while a batch is encoded form the next batch.
The frames go straight to the encoder's inbox key (no sim), so the sim's
step time does not hide the encoder's.
"""

from __future__ import annotations

import math
import queue
import tempfile
import time
from contextlib import closing
from pathlib import Path

import msgpack
import numpy as np
import torch
import zenoh

from encoder_service import DEFAULT_CHECKPOINT
from encoder_service.model import CMVAE, make_checkpoint
from encoder_service.service import EncoderSettings
from services.keys import Keys
from services.messages import BatchItem, BatchMsg, LatentMsg, ObservationMsg
from services.presence import Roster
from services.procs import ProcessGroup
from services.session import open_session
from services.settings import ZenohSettings, load
from services.telemetry import Telemetry

IDENT = "enc-bench"
METRICS_PERIOD_S = 0.5
PHASE_S = 3.0  # seconds per measurement phase
ROUNDS = 3  # batch-1 and batched phases alternate this many times
_STILL = Telemetry(
    rover_pos=(0.0, 0.0, -4.0),
    rover_quat=(1.0, 0.0, 0.0, 0.0),
    rover_forward=(1.0, 0.0, 0.0),
    rover_lin_vel=(0.0, 0.0, 0.0),
    rover_ang_vel=(0.0, 0.0, 0.0),
    target_pos=(6.0, 0.0, -4.0),
    target_quat=(1.0, 0.0, 0.0, 0.0),
    target_forward=(1.0, 0.0, 0.0),
    target_lin_vel=(0.0, 0.0, 0.0),
    target_in_frustum=True,
    collided=False,
    sim_time=0.0,
)


def checkpoint_for_bench(tmp: Path) -> tuple[Path, str]:
    """The shipped CMVAE when present; otherwise a freshly initialised one (same architecture, same cost)."""
    if DEFAULT_CHECKPOINT.is_file():
        return DEFAULT_CHECKPOINT, f"shipped {DEFAULT_CHECKPOINT.relative_to(Path(__file__).parents[1])}"
    torch.manual_seed(0)
    path = tmp / "cmvae-fresh.pt"
    torch.save(make_checkpoint(CMVAE(), beta=8.0, epoch=0, val_loss=math.nan, metrics={}), path)
    return path, "freshly initialised (no shipped model found)"


def _only_item(payload: bytes) -> BatchItem:
    """A group of one's item (each env here is a group of its own)."""
    return BatchMsg.decode(payload).items[0]


class LockstepFeeder:
    """Drives ``n`` lock-step environments against one encoder and counts the latents that come back."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.session, self.keys = session, keys
        self.latents: queue.Queue[LatentMsg] = queue.Queue()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscriber = session.declare_subscriber(
            keys.latent("train", "*"), lambda s: self.latents.put(LatentMsg.from_item(_only_item(s.payload.to_bytes())))
        )
        self._images = np.random.default_rng(0).integers(0, 256, size=(32, 64, 64, 3), dtype=np.uint8)
        self._seq = 0

    def _send(self, env: str) -> None:
        if env not in self._publishers:
            self._publishers[env] = self.session.declare_publisher(
                self.keys.obs("train", env, IDENT), congestion_control=zenoh.CongestionControl.BLOCK
            )
        self._seq += 1
        image = self._images[self._seq % len(self._images)]
        frame = ObservationMsg(env, 1, self._seq, _STILL, image)
        self._publishers[env].put(BatchMsg.alone(BatchItem.of(env, frame)).encode())  # as a sim answers one env

    def feed(self, envs: int, seconds: float, limit: int = 0) -> tuple[int, int]:
        """Drive ``envs`` lock-step environments for ``seconds`` (or ``limit`` latents, if given), then drain.

        Returns (latents that came back in time, latents in all): only the
        first count towards the rate; the rest are the frames still in flight.
        """
        deadline = time.perf_counter() + seconds
        for env in range(envs):
            self._send(str(env))
        in_time, outstanding = 0, envs
        while outstanding:
            latent = self.latents.get(timeout=30)
            if time.perf_counter() < deadline and (not limit or in_time < limit):
                in_time += 1
                self._send(latent.env)
            else:
                outstanding -= 1
        return in_time, in_time + envs

    def close(self) -> None:
        self._subscriber.undeclare()
        for publisher in self._publishers.values():
            publisher.undeclare()


class EncoderCounters:
    """The encoder's own published counters, to report the batch sizes it formed in each phase."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self._latest: dict = {}
        self._subscriber = session.declare_subscriber(keys.metrics("encoder", IDENT), self._on_metrics)

    def _on_metrics(self, sample: zenoh.Sample) -> None:
        self._latest = msgpack.unpackb(sample.payload.to_bytes())

    def settled(self) -> dict:
        """A snapshot published after everything so far was counted."""
        time.sleep(2.5 * METRICS_PERIOD_S)
        return dict(self._latest)

    def close(self) -> None:
        self._subscriber.undeclare()


def run(steps: int = 0, envs: int = 16) -> dict:
    """Batch 1 and ``envs`` environments, alternating ``ROUNDS`` times so both see the same background load.

    Each phase runs ``PHASE_S`` seconds, or ``steps`` images when given.
    """
    with tempfile.TemporaryDirectory(prefix="swimm-bench-") as tmp, ProcessGroup(Path(tmp) / "logs") as group:
        checkpoint, model = checkpoint_for_bench(Path(tmp))
        endpoint = group.start_router()
        settings = ZenohSettings(connect=[endpoint], namespace="swimm/bench-encoder")
        encoder = load(EncoderSettings)  # what the encoder process reads too (defaults < SWIMM_* variables)
        group.start(
            "encoder", "encoder", "--connect", endpoint, "--namespace", settings.namespace,
            "--checkpoint", str(checkpoint), "--ident", IDENT, "--metrics-period-s", str(METRICS_PERIOD_S),
        )  # fmt: skip
        keys = Keys(settings.namespace)
        timed = {1: [0, 0.0], envs: [0, 0.0]}  # envs -> [latents in time, seconds]
        encoded = {1: 0, envs: 0}  # envs -> latents in all, for the batch sizes
        with (
            open_session(settings, role="bench") as session,
            Roster(session, keys, "encoder") as encoders,
            closing(LockstepFeeder(session, keys)) as feeder,
            closing(EncoderCounters(session, keys)) as counters,
        ):
            encoders.wait_for(1, timeout_s=60)
            feeder.feed(envs, 2.0)  # warm-up: TorchScript's profiling runs, allocator, caches
            before = counters.settled()
            for _ in range(ROUNDS):
                for n in (1, envs):
                    started = time.perf_counter()
                    in_time, total = feeder.feed(n, 3600.0 if steps else PHASE_S, limit=steps)
                    timed[n][0] += in_time
                    timed[n][1] += time.perf_counter() - started if steps else PHASE_S
                    encoded[n] += total
            after = counters.settled()
            group.check_alive()
    batch1, batched = (timed[n][0] / timed[n][1] for n in (1, envs))
    batched_batches = after.get("batches", 0) - before.get("batches", 0) - encoded[1]  # batch 1 is one per frame
    return {
        "batch1_images_per_s": round(batch1, 1),
        "batched_images_per_s": round(batched, 1),
        "ratio": round(batched / batch1, 2),
        "envs": envs,
        "batched_mean_batch": round(encoded[envs] / batched_batches, 2) if batched_batches > 0 else math.nan,
        "latency_p50_ms": round(after.get("latency_p50_ms", math.nan), 3),
        "seconds_per_phase": PHASE_S if not steps else None,
        "rounds": ROUNDS,
        "max_batch": encoder.max_batch,
        "max_wait_ms": encoder.max_wait_ms,
        "threads": encoder.threads,
        "model": model,
    }
