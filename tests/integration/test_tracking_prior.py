"""A tracking encoder's prior carried through the loop, across real processes: router, sim and tracking encoders
(`swimm encoder` on a --track checkpoint or the pod detector), the learner's EnvLink in the test.

The encoder keeps no state: the prior travels with each env's messages (the latent's next_prior, handed back on the
next action, echoed by the sim into its observation), so an encoder killed mid-episode loses nothing.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from encoder_service import POD_DETECTOR
from encoder_service.inference import LatentEncoder, open_encoder
from services.messages import ActionMsg, LatentMsg, ObservationMsg, batch_messages
from tests.integration.conftest import start_encoders, start_sim

pytestmark = pytest.mark.slow

STEP_TIMEOUT_S = 2.0
SURGE_AND_TURN = (0.0, 0.0, 0.5, 0.4)


class Tap:
    """Every action, observation and latent of the train channel, by (env, ep, seq): the last one heard, and for
    observations the route (encoder) each went to."""

    def __init__(self, client) -> None:
        self.actions: dict[tuple[str, int, int], ActionMsg] = {}
        self.observations: dict[tuple[str, int, int, str], ObservationMsg] = {}
        self.latents: dict[tuple[str, int, int], LatentMsg] = {}
        self._lock = threading.Lock()
        train = f"{client.keys.namespace}/train/*"
        self._subscribers = [
            client.session.declare_subscriber(f"{train}/action", self._on(self.actions, ActionMsg.from_item)),
            client.session.declare_subscriber(f"{train}/obs/*", self._on(self.observations, ObservationMsg.from_item)),
            client.session.declare_subscriber(f"{train}/latent", self._on(self.latents, LatentMsg.from_item)),
        ]

    def _on(self, seen: dict, read):
        def record(sample) -> None:
            route = str(sample.key_expr).rsplit("/", 1)[-1]
            with self._lock:
                for env, msg in batch_messages(sample.payload.to_bytes(), read):
                    key = (env, msg.ep, msg.seq, route) if seen is self.observations else (env, msg.ep, msg.seq)
                    seen[key] = msg

        return record

    def close(self) -> None:
        time.sleep(0.5)  # let the last messages reach the tap
        for subscriber in self._subscribers:
            subscriber.undeclare()


def test_the_link_hands_each_next_prior_back_on_the_next_action_and_a_reset_clears_it(
    group, connect_client, namespace, tracking_checkpoint
):
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", "2", "--eval-envs", "0")
    start_encoders(group, endpoint, namespace, tracking_checkpoint, ("enc-a",))
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    roster = client.roster("encoder")
    roster.wait_for(1, timeout_s=90)
    tap = Tap(client)
    link = client.link(envs=["0", "1"], group="g", encoders=roster)
    for index in range(2):
        link.claim(index=index)
        link.send_reset(1, 10 + index, index=index)
        link.wait()
    for _ in range(4):
        link.send([SURGE_AND_TURN, (0.0, 0.0, 0.5, -0.4)])
        link.wait()
    link.send_reset(2, 12)  # env 0 only
    assert link.priors[0] is None and link.priors[1] is not None  # env 1's episode goes on
    link.wait()
    link.send([SURGE_AND_TURN, SURGE_AND_TURN])
    link.wait()
    link.close()
    tap.close()

    steps = [("0", 1, seq) for seq in range(1, 5)] + [("0", 2, 1)] + [("1", 1, seq) for seq in range(1, 6)]
    for env, ep, seq in steps:  # every action carried the next_prior of the latent before it; the sim echoed it
        prior = tap.latents[(env, ep, seq - 1)].next_prior
        assert prior is not None and tap.actions[(env, ep, seq)].prior == prior, (env, ep, seq)
        assert tap.observations[(env, ep, seq, "enc-a")].prior == prior
    # The new episode's first frame was encoded at the image centre, not at the previous episode's prior.
    reset = tap.observations[("0", 2, 0, "enc-a")]
    assert reset.prior is None
    at_centre, _ = LatentEncoder(tracking_checkpoint, threads=1).encode(reset.image[None], [0.0])
    np.testing.assert_allclose(tap.latents[("0", 2, 0)].mu, at_centre[0], atol=1e-4)


@pytest.mark.parametrize("served", ["tracking-cmvae", "pod-detector"])
def test_a_tracking_encoder_killed_mid_episode_loses_no_perception_state(
    group, connect_client, namespace, tracking_checkpoint, served
):
    """A tracking CMVAE's prior (an azimuth) and the pod tracker's (its every track, 64 numbers, over a pod of 4)."""
    checkpoint, world = {
        "tracking-cmvae": (tracking_checkpoint, ()),
        "pod-detector": (POD_DETECTOR, ("--dolphin-pod-size", "4")),
    }[served]
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--train-envs", "1", "--eval-envs", "0", *world)
    encoders = start_encoders(group, endpoint, namespace, checkpoint, ("enc-a", "enc-b"))
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    roster = client.roster("encoder")
    roster.wait_for(len(encoders), timeout_s=90)
    tap = Tap(client)
    link = client.link(encoders=roster, step_timeout_s=STEP_TIMEOUT_S, max_retries=20)
    link.claim()
    link.send_reset(1, 7)
    link.wait()
    rounds = 6
    for _ in range(rounds):
        link.send([SURGE_AND_TURN])
        link.wait()
    prior = link.priors[0]  # the last latent's next_prior: where the target was last seen
    time.sleep(0.3)
    serving = tap.latents[("0", 1, rounds)].encoder
    assert tap.latents[("0", 1, rounds)].next_prior == prior

    # Frozen first, so it dies holding the frame the link waits for: the retry is answered from the sim's cache.
    os.kill(encoders[serving].process.pid, signal.SIGSTOP)
    link.send([SURGE_AND_TURN])
    time.sleep(0.3)
    group.stop(encoders[serving], kill=True)
    (frame,) = link.wait()
    link.close()
    tap.close()

    (survivor,) = set(encoders) - {serving}
    assert link.retries >= 1 and tap.latents[("0", 1, rounds + 1)].encoder == survivor
    observation = tap.observations[("0", 1, rounds + 1, survivor)]
    assert observation.prior == prior  # the retry carried the prior to the survivor
    reference = open_encoder(checkpoint, threads=1)
    expected, _, state = reference.track(observation.image[None], np.reshape(prior, (1, *reference.prior_shape)))
    np.testing.assert_allclose(frame.mu, expected[0], atol=1e-4)
    np.testing.assert_allclose(tap.latents[("0", 1, rounds + 1)].next_prior, state.ravel(), atol=1e-3)
    # What a fresh encoder without the prior would say: the image centre's dolphin, or no track yet.
    fresh, _, fresh_state = reference.track(observation.image[None])
    assert not (np.allclose(frame.mu, fresh[0], atol=1e-3) and np.allclose(state, fresh_state, atol=1e-3))
