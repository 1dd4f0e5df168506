"""`swimm encoder` in-process against a real `swimm router` process: latents, batching and refusals.

The frames are published by a test session exactly as the sim publishes
them (each a group of one: a BatchMsg of the env's ObservationMsg on
``<ns>/<channel>/<env>/obs/<encoder id>``), so
what is tested is the service's own routing, batching, codec and
error handling over real Zenoh; the sim itself is covered elsewhere.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
import zenoh

from encoder_service import POD_DETECTOR
from encoder_service.inference import DEFAULT_CHECKPOINT as SHIPPED_CMVAE
from encoder_service.inference import LatentEncoder
from encoder_service.model import CMVAE, make_checkpoint
from encoder_service.pod_detector_train import load_pod_dataset
from encoder_service.pod_encoder import PodEncoder
from encoder_service.service import EncoderService, EncoderSettings, LatentBatcher, _Frame
from learner_service.live_encoders import check_live_encoders
from services.keys import Keys
from services.messages import BatchItem, BatchMsg, LatentMsg, ObservationMsg, image_to_fields
from services.pod_tracker import STATE_SIZE
from services.presence import Roster, ask_about
from services.results import file_sha256
from services.settings import ZenohSettings
from services.telemetry import Telemetry
from tests.encoder.pod_testdata import render_pod_dataset

IDENT = "enc-test"
BLOCK = zenoh.CongestionControl.BLOCK


def telemetry(step: int) -> Telemetry:
    """Distinct telemetry per step, so a pass-through mix-up would show."""
    return Telemetry(
        rover_pos=(float(step), 0.5, -4.0),
        rover_quat=(1.0, 0.0, 0.0, 0.0),
        rover_forward=(1.0, 0.0, 0.0),
        rover_lin_vel=(0.1, 0.0, 0.0),
        rover_ang_vel=(0.0, 0.0, 0.01),
        target_pos=(6.0, 0.0, -4.0),
        target_quat=(0.0, 0.0, 0.0, 1.0),
        target_forward=(-1.0, 0.0, 0.0),
        target_lin_vel=(0.0, 1.0, 0.0),
        target_in_frustum=step % 2 == 0,
        collided=False,
        sim_time=0.02 * step,
    )


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(3)
    path = tmp_path_factory.mktemp("encoder-service") / "cmvae.pt"
    torch.save(make_checkpoint(CMVAE(n_z=10), beta=8.0, epoch=1, val_loss=1.0, metrics={}), path)
    return path


@pytest.fixture
def start_service(
    zenoh_router: str, zenoh_settings: Callable[[str], ZenohSettings], checkpoint: Path
) -> Iterator[Callable[..., EncoderService]]:
    with ExitStack() as started:

        def start(**overrides) -> EncoderService:
            fields = {"zenoh": zenoh_settings(zenoh_router), "checkpoint": str(checkpoint), "ident": IDENT}
            return started.enter_context(EncoderService(EncoderSettings(**fields | {"threads": 1} | overrides)))

        yield start


class Feeder:
    """The sim's side (publishes frames to the encoder) and the learner's (collects latents and refusals)."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.session, self.keys = session, keys
        self.latents: queue.Queue[LatentMsg] = queue.Queue()
        self.errors: queue.Queue[BatchItem] = queue.Queue()  # refused items
        self._subs = [session.declare_subscriber(f"{keys.namespace}/*/*/latent", self._on_latents)]
        self._encoders = Roster(session, keys, "encoder")

    def _on_latents(self, sample: zenoh.Sample) -> None:
        for item in BatchMsg.decode(sample.payload.to_bytes()).items:
            if item.error:
                self.errors.put(item)
            else:
                self.latents.put(LatentMsg.from_item(item))

    def send(self, env: str, item: BatchItem, channel: str = "train") -> None:
        """``item`` as env ``env``'s group of one, as the sim sends a reset's observation."""
        self.send_raw(env, BatchMsg.alone(item).encode(), channel)

    def send_raw(self, group: str, payload: bytes, channel: str = "train") -> None:
        self._encoders.wait_for(1, timeout_s=20)  # the encoder announces itself once it listens
        self.session.put(self.keys.obs(channel, group, IDENT), payload, congestion_control=BLOCK)  # as the sim does

    def frame(self, env: str, seq: int, image: np.ndarray, prior: tuple[float, ...] | None = None) -> BatchItem:
        return BatchItem.of(env, ObservationMsg(env, 1, seq, telemetry(seq), image, prior=prior))

    def take_latents(self, count: int, timeout_s: float = 20.0) -> list[LatentMsg]:
        deadline = time.monotonic() + timeout_s
        got: list[LatentMsg] = []
        while len(got) < count:
            try:
                got.append(self.latents.get(timeout=max(deadline - time.monotonic(), 0.01)))
            except queue.Empty:
                raise AssertionError(f"{len(got)} of {count} latents within {timeout_s} s") from None
        return got


@pytest.fixture
def feeder(zenoh_router: str, zenoh_session, namespace: str) -> Feeder:
    return Feeder(zenoh_session(zenoh_router), Keys(namespace))


def images(count: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(count, 64, 64, 3), dtype=np.uint8)


def test_latents_match_the_encoder_on_the_same_images(start_service, feeder: Feeder, checkpoint: Path) -> None:
    start_service(max_wait_ms=5.0)
    frames = images(12, seed=4)
    for seq, image in enumerate(frames):
        feeder.send(str(seq % 3), feeder.frame(str(seq % 3), seq, image), "eval" if seq % 2 else "train")
    by_seq = {msg.seq: msg for msg in feeder.take_latents(len(frames))}
    assert sorted(by_seq) == list(range(len(frames)))  # each frame encoded once
    expected_mu, expected_logvar = LatentEncoder(checkpoint, threads=1).encode(frames)
    for seq, msg in by_seq.items():
        assert (msg.env, msg.ep, msg.encoder) == (str(seq % 3), 1, IDENT)
        assert msg.telemetry == telemetry(seq)  # passed through unchanged
        assert msg.next_prior is None  # the model does not track
        np.testing.assert_allclose(msg.mu, expected_mu[seq], rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(msg.logvar, expected_logvar[seq], rtol=1e-4, atol=1e-5)
    assert feeder.latents.empty() and feeder.errors.empty()


def test_a_tracking_encoder_reads_each_frames_prior_and_answers_the_next(
    start_service, feeder: Feeder, tracking_checkpoint: Path
) -> None:
    start_service(checkpoint=str(tracking_checkpoint), max_wait_ms=20.0)
    image = images(1, seed=8)[0]
    priors = [None, 0.0, 25.0, -25.0]  # one frame seen with each; None: the image centre, as 0.0
    for seq, prior in enumerate(priors):
        feeder.send(str(seq), feeder.frame(str(seq), seq, image, None if prior is None else (prior,)))
    by_seq = {msg.seq: msg for msg in feeder.take_latents(len(priors))}
    reference = LatentEncoder(tracking_checkpoint, threads=1)
    for seq, prior in enumerate(priors):
        expected, _, next_prior = reference.track(image[None], [prior or 0.0])
        np.testing.assert_allclose(by_seq[seq].mu, expected[0], rtol=1e-4, atol=1e-4)
        assert by_seq[seq].next_prior == pytest.approx((next_prior[0],), abs=1e-3)
    assert not np.allclose(by_seq[2].mu, by_seq[1].mu, atol=1e-3)  # the prior changed what it described


def test_a_pod_detector_serves_its_tracker_state_as_each_frames_prior(
    start_service, feeder: Feeder, tmp_path: Path
) -> None:
    frames = load_pod_dataset(render_pod_dataset(tmp_path / "pod", count=3, shard_size=3))["images"]
    start_service(checkpoint=str(POD_DETECTOR), max_wait_ms=20.0)
    reference = PodEncoder(POD_DETECTOR)
    _, _, engaged = reference.track(frames[:1])  # the state after an episode's first frame
    feeder.send("0", feeder.frame("0", 1, frames[1]))  # a new episode's first frame: no prior
    feeder.send("1", feeder.frame("1", 1, frames[1], tuple(engaged[0].tolist())))
    by_env = {msg.env: msg for msg in feeder.take_latents(2)}
    for env, prior in (("0", None), ("1", engaged)):
        expected, _, state = reference.track(frames[1][None], prior)
        np.testing.assert_allclose(by_env[env].mu, expected[0], atol=1e-5)
        assert by_env[env].next_prior == pytest.approx(tuple(state[0].tolist()), abs=1e-5)
    assert by_env["0"].next_prior != by_env["1"].next_prior  # the state carried, not the frame alone
    feeder.send("2", feeder.frame("2", 1, frames[2], (1.0, 2.0)))
    refused = feeder.errors.get(timeout=10)
    assert refused.env == "2" and f"prior of 2 numbers; {POD_DETECTOR} reads {STATE_SIZE}" in refused.error


def test_frames_arriving_together_are_encoded_in_batches(start_service, feeder: Feeder) -> None:
    start_service(max_batch=8, max_wait_ms=50.0, metrics_period_s=0.2)
    published: queue.Queue[dict] = queue.Queue()
    metrics_sub = feeder.session.declare_subscriber(
        feeder.keys.metrics("encoder", IDENT), lambda s: published.put(msgpack.unpackb(s.payload.to_bytes()))
    )
    count = 48
    for seq, image in enumerate(images(count, seed=5)):
        feeder.send(str(seq % 16), feeder.frame(str(seq % 16), seq, image))
    assert sorted(msg.seq for msg in feeder.take_latents(count)) == list(range(count))
    snap: dict = {}
    deadline = time.monotonic() + 10
    while snap.get("images") != count and time.monotonic() < deadline:  # what <ns>/metrics/encoder/<id> says
        snap = published.get(timeout=5)
    metrics_sub.undeclare()
    assert snap["images"] == count and (snap["role"], snap["id"]) == ("encoder", IDENT)
    assert snap["batches"] < count and 1 < snap["batch_size_max"] <= 8  # batched, never above max_batch
    assert snap["batch_size_mean"] == pytest.approx(count / snap["batches"])
    assert snap["latency_p50_ms"] > 0 and snap["images_per_s"] > 0


def test_bad_frames_are_refused_with_reasons_and_the_service_keeps_serving(start_service, feeder: Feeder) -> None:
    service = start_service()
    good = images(1, seed=6)[0]

    def item(frame: np.ndarray, **overrides) -> BatchItem:
        fields = {"t": 0.0, "telemetry": telemetry(9).to_dict(), **image_to_fields(frame)}
        return BatchItem("2", 4, 9, fields | overrides)

    bad = {
        "shape": item(images(1, seed=7)[0, :32]),  # a 32x64 frame
        "dtype": item(good, dtype="float32"),
        "bytes": item(good, image=good.tobytes()[:-5]),
        "telemetry": item(good, telemetry={"rover_pos": [0, 0, 0]}),
        "'t'": item(good, t="noon"),
    }
    feeder.send("2", feeder.frame("2", 9, good), channel="replay")  # not a channel: refused, with no one to tell
    # Not a group's message, not msgpack, another version: no env's item to answer, so refused with no one to tell.
    for unreadable in (
        msgpack.packb(feeder.frame("2", 9, good).body),
        b"\xc1\xff not msgpack",
        msgpack.packb({"v": 99, "items": []}),
    ):
        feeder.send_raw("2", unreadable)
    for refused_item in bad.values():
        feeder.send("2", refused_item)
    refused = [feeder.errors.get(timeout=10) for _ in bad]
    for what, item in zip(bad, refused, strict=True):
        assert what in item.error.lower(), (what, item.error)
        assert f"encoder {IDENT}" in item.error and (item.env, item.ep, item.seq) == ("2", 4, 9)  # names its step
    sim_refused = BatchItem("2", 4, 10, error="env train/2 is held by learner-1")
    feeder.send_raw("2", BatchMsg("2", "sim-1", (sim_refused,), to="learner-1").encode())
    assert feeder.errors.get(timeout=10) == sim_refused  # the sim's refusal passed on as it came
    feeder.send("2", feeder.frame("2", 10, good))
    (latent,) = feeder.take_latents(1)
    assert (latent.env, latent.seq) == ("2", 10)
    snap = service.metrics.snapshot()
    assert snap["errors_refused"] == len(bad) + 4 and snap["images"] == 1
    assert feeder.errors.empty()


def test_the_batcher_caps_batches_and_drains_before_closing() -> None:
    batcher = LatentBatcher(max_batch=4, max_wait_ms=0.0)
    for i in range(6):
        batcher.put(_Frame(str(i), b"", 0.0))
    batcher.close()
    assert [len(b) for b in iter(batcher.next_batch, None)] == [4, 2]  # no wait needed once frames are queued
    waiting = LatentBatcher(max_batch=4, max_wait_ms=30.0)
    waiting.put(_Frame("a", b"", 0.0))
    started = time.perf_counter()
    assert len(waiting.next_batch()) == 1
    assert time.perf_counter() - started >= 0.025  # a lone frame waited max_wait_ms for company
    assert waiting.next_batch(idle_timeout_s=0.01) == []
    with pytest.raises(ValueError, match="max_batch"):
        LatentBatcher(max_batch=0, max_wait_ms=1.0)


def test_a_live_encoder_says_which_cmvae_it_runs_and_a_run_on_another_is_refused(
    start_service, zenoh_router: str, zenoh_session, namespace: str, checkpoint: Path
) -> None:
    """Over Zenoh a learner cannot see the encoder's file: the encoder answers its path and hash, and a run that
    would record another CMVAE is refused naming both files and the encoder."""
    start_service()
    session, keys = zenoh_session(zenoh_router), Keys(namespace)
    Roster(session, keys, "encoder").wait_for(1, timeout_s=20)
    answers = ask_about(session, keys, "encoder")
    assert answers == {IDENT: {"checkpoint": str(checkpoint), "sha256": file_sha256(checkpoint)}}
    check_live_encoders(answers, checkpoint, "this run")  # the same file: accepted
    with pytest.raises(ValueError, match=rf"this run reads encoder {SHIPPED_CMVAE}.*{IDENT} runs {checkpoint}"):
        check_live_encoders(answers, SHIPPED_CMVAE, "this run")
