"""`swimm record` and `swimm replay` over real processes: a lock-step episode through a sim and an encoder is
recorded to MCAP, read back with the mcap library, scored offline, replayed bit-exact, and replayed into a new
encoder that gives its latents again."""

from __future__ import annotations

import base64
import json
import threading
import time

import cv2
import numpy as np
import pytest
import torch
from mcap.reader import make_reader

from encoder_service.model import CMVAE, make_checkpoint
from eval_service.offline import score_recording
from learner_service.task import REWARDS, TrackingTask
from services.messages import LatentMsg, ObservationMsg, batch_messages
from services.record import recorded_namespace, recorded_samples
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow

STEPS = 20


def start_encoder(group, endpoint: str, namespace: str, checkpoint, name: str):
    return group.start(name, "encoder", "--connect", endpoint, "--namespace", namespace, "--checkpoint",
                       str(checkpoint), "--ident", "enc-0", "--threads", "1")  # fmt: skip


def only(payload: bytes, decode):
    """The message of a single env's step message (its group of one)."""
    ((_, msg),) = batch_messages(payload, decode)
    return msg


def wait_for_line(service, text: str, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while text not in service.log_path.read_text():
        assert service.alive and time.monotonic() < deadline, service.log_tail()
        time.sleep(0.2)


def test_a_recorded_episode_replays_bit_exact_and_through_a_new_encoder(group, connect_client, namespace, tmp_path):
    checkpoint = tmp_path / "cmvae.pt"
    torch.manual_seed(0)
    torch.save(make_checkpoint(CMVAE(), beta=8.0, epoch=0, val_loss=1.0, metrics={}), checkpoint)
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", "1", "--eval-envs", "0")
    start_encoder(group, endpoint, namespace, checkpoint, "encoder")
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    encoders = client.roster("encoder")
    encoders.wait_for(1, timeout_s=90)
    out = tmp_path / "episode.mcap"
    recorder = group.start("recorder", "record", "--connect", endpoint, "--namespace", namespace, "--out", str(out))
    wait_for_line(recorder, "recording")
    time.sleep(1.0)  # the subscription reaches the router

    link = client.link("train", "0", encoders=encoders, step_timeout_s=5.0)
    link.claim()
    link.send_reset(1, 4242)
    live = link.wait()
    for step in range(STEPS):
        link.send([(0.0, 0.0, 0.5, 0.3 * (-1) ** step)])
        live += link.wait()
    time.sleep(0.5)
    assert group.stop(recorder) == 0, recorder.log_tail()

    # What the file holds, read with the mcap library: the wire's bytes on each key, frames as images.
    assert recorded_namespace(out) == namespace
    samples = recorded_samples(out)
    by_key: dict[str, list[bytes]] = {}
    for key, payload, _ in samples:
        by_key.setdefault(key, []).append(payload)
    prefix = f"{namespace}/train/0"
    assert len(by_key[f"{prefix}/action"]) == STEPS and len(by_key[f"{prefix}/obs/enc-0"]) == STEPS + 1
    recorded_latents = [only(payload, LatentMsg.from_item) for payload in by_key[f"{prefix}/latent"]]
    assert [(m.ep, m.seq) for m in recorded_latents] == [(1, seq) for seq in range(STEPS + 1)]
    for reply, msg in zip(live, recorded_latents, strict=True):
        assert np.array_equal(reply.mu, np.asarray(msg.mu, np.float32))
    with out.open("rb") as handle:
        images = [(schema, message) for schema, channel, message in make_reader(handle).iter_messages()
                  if channel.topic == f"{prefix}/obs/enc-0/image"]  # fmt: skip
    assert len(images) == STEPS + 1 and images[0][0].name == "foxglove.CompressedImage"
    first = json.loads(images[0][1].data)
    png = np.frombuffer(base64.b64decode(first["data"]), np.uint8)
    frame = cv2.cvtColor(cv2.imdecode(png, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    observed = only(by_key[f"{prefix}/obs/enc-0"][0], ObservationMsg.from_item).image
    assert first["format"] == "png" and np.array_equal(frame, observed)

    # Scored offline as `swimm eval --recording` does: the return the live steps earned, step by step.
    (row,) = score_recording(out)
    expected = sum(REWARDS["swimm2"](*(TrackingTask.info(r.telemetry)[k] for k in ("d", "theta"))) for r in live[1:])
    assert (row["label"], row["episode"], row["steps"]) == ("train/0", 1, STEPS)
    assert row["return"] == pytest.approx(expected, rel=1e-12)

    # Replayed into another namespace, observations only, where a new encoder serves: the same bytes arrive, and
    # the encoder gives the recorded latents again.
    target = f"{namespace}-replay"
    start_encoder(group, endpoint, target, checkpoint, "encoder-replay")
    watcher = connect_client(endpoint)
    heard: dict[str, list[bytes]] = {}
    lock = threading.Lock()

    def on_sample(sample) -> None:
        with lock:
            heard.setdefault(str(sample.key_expr), []).append(sample.payload.to_bytes())

    subscriber = watcher.session.declare_subscriber(f"{target}/**", on_sample)
    deadline = time.monotonic() + 90
    while not any(token.startswith(f"{target}/@live/encoder") for token in _tokens(watcher, target)):
        assert time.monotonic() < deadline, "the replay namespace's encoder never came up"
        time.sleep(0.2)
    time.sleep(2.0)  # the new encoder's subscription reaches the router (its token can come first)
    replay = group.start("replay", "replay", str(out), "--connect", endpoint, "--namespace", target,
                         "--no-namespace-from-file", "--keys", "*/*/obs/*", "--speed", "recorded")  # fmt: skip
    assert replay.process.wait(timeout=60) == 0, replay.log_tail()
    deadline = time.monotonic() + 30
    while len(heard.get(f"{target}/train/0/latent", [])) < STEPS + 1:
        assert time.monotonic() < deadline, f"latents heard: {len(heard.get(f'{target}/train/0/latent', []))}"
        time.sleep(0.2)
    subscriber.undeclare()
    assert heard[f"{target}/train/0/obs/enc-0"] == by_key[f"{prefix}/obs/enc-0"]  # bit-exact, in order
    assert f"{target}/train/0/action" not in heard  # --keys kept the actions out
    replayed = sorted((only(p, LatentMsg.from_item) for p in heard[f"{target}/train/0/latent"]), key=lambda m: m.seq)
    for again, recorded in zip(replayed, recorded_latents, strict=True):
        assert (again.ep, again.seq) == (recorded.ep, recorded.seq)
        np.testing.assert_allclose(again.mu, recorded.mu, atol=1e-5)


def _tokens(client, namespace: str) -> list[str]:
    return [str(reply.ok.key_expr) for reply in client.session.liveliness().get(f"{namespace}/@live/**") if reply.ok]
