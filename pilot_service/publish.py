"""`swimm pilot --publish`: the frames the policy acted on, published as a sim publishes an env's observations.

A real dive then feeds everything swimm has for simulated ones, unchanged: an encoder answers each frame with its
latent on the env's latent key (each frame goes as the env's group of one, as a sim sends a reset's), the live
view and `swimm record` see the observations and latents, and a recording of the dive replays like a sim's. The
frames go out as env ``env`` of the eval channel, one episode, ``seq`` the frame's number, each routed to the live
encoder that rendezvous hashing picks for that env (as the learner routes its steps), or ``direct`` while no
encoder is live: a dive never waits for one. A real camera has no ground truth, so the telemetry is
:meth:`services.telemetry.Telemetry.unknown` (NaN but for the time).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import zenoh

from services.keys import Keys
from services.lifecycle import Owner
from services.messages import DIRECT_ROUTE, BatchItem, BatchMsg, ObservationMsg
from services.presence import Roster, rendezvous_choice
from services.session import open_session
from services.settings import ZenohSettings
from services.telemetry import Telemetry

log = logging.getLogger(__name__)

CHANNEL = "eval"  # not a training env: nothing learns from footage without a reward


class FramePublisher(Owner):
    def __init__(self, settings: ZenohSettings, env: str) -> None:
        self.session = self.resources.enter_context(open_session(settings, role="pilot"))
        self.keys = Keys(settings.namespace)
        self.env = env
        self.encoders = self.resources.enter_context(Roster(self.session, self.keys, "encoder"))
        self.started = time.monotonic()
        log.info("publishing the policy's frames as %s/%s/%s", settings.namespace, CHANNEL, env)

    def publish(self, frame: np.ndarray, number: int) -> None:
        """Frame ``number`` (as the policy saw it) to the encoder that serves this env, or ``direct``."""
        members = self.encoders.members()
        route = rendezvous_choice(f"{CHANNEL}/{self.env}", members) if members else DIRECT_ROUTE
        telemetry = Telemetry.unknown(time.monotonic() - self.started)
        message = ObservationMsg(env=self.env, ep=1, seq=number, telemetry=telemetry, image=frame)
        payload = BatchMsg.alone(BatchItem.of(self.env, message)).encode()
        # DROP: a congested network loses a frame of the feed rather than stalling the control loop.
        self.session.put(
            self.keys.obs(CHANNEL, self.env, route), payload, congestion_control=zenoh.CongestionControl.DROP
        )
