"""A learner-side process for the deployment tests: drives sim envs through the encoders and logs every reply.

    python -m tests.deploy.lockstep_driver --connect tcp/10.77.0.1:7447 --namespace swimm/x --envs 4 \\
        --steps 300 --out replies.jsonl

It claims ``--envs`` train envs, resets them, and steps them all in lock-step (send every action, then
gather every reply, as the vectorised proxy env does) for ``--steps`` steps, with the links' own
retry and re-routing. Each accepted reply is one JSON line (env, ep, seq, sim_time, wall time t), flushed at
once so a test can watch progress and cut links mid-run; the last line holds each link's retries, dropped
duplicates and which encoder encoded each step. The test checks the log itself: no (ep, seq) lost,
repeated or out of order.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time

import numpy as np

from learner_service.link import EnvLink, new_holder_id
from services.keys import Keys
from services.messages import LatentMsg, batch_messages
from services.presence import Roster, announce
from services.session import open_session
from services.settings import ZenohSettings


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True)
    parser.add_argument("--namespace", required=True)
    parser.add_argument("--envs", type=int, default=2)
    parser.add_argument("--encoders", type=int, default=2, help="live encoders to wait for before starting")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--step-timeout-s", type=float, default=1.0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s driver %(levelname)s %(name)s: %(message)s")

    session = open_session(ZenohSettings(connect=[args.connect], namespace=args.namespace), role="driver")
    keys = Keys(args.namespace)
    holder = new_holder_id("learner")
    token = announce(session, keys, "learner", holder)
    encoders = Roster(session, keys, "encoder")
    Roster(session, keys, "sim").wait_for(1, timeout_s=120)
    encoders.wait_for(args.encoders, timeout_s=120)

    # Which encoder produced each latent: the link keeps only (ep, seq), so listen beside it.
    encoded_by: dict[tuple[str, int, int], str] = {}
    lock = threading.Lock()

    def note_encoder(sample) -> None:
        with lock:
            for env, msg in batch_messages(sample.payload.to_bytes(), LatentMsg.from_item):
                encoded_by.setdefault((env, msg.ep, msg.seq), msg.encoder)

    latent_sub = session.declare_subscriber(f"{args.namespace}/train/*/latent", note_encoder)
    links = [
        EnvLink(
            session,
            keys,
            "train",
            [str(i)],
            holder,
            encoded=True,
            encoders=encoders,
            step_timeout_s=args.step_timeout_s,
            max_retries=60,
        )  # fmt: skip
        for i in range(args.envs)
    ]
    rng = np.random.default_rng(0)
    with open(args.out, "w") as out:

        def record(link: EnvLink) -> None:
            (reply,) = link.wait()
            line = {"env": link.group, "ep": link.ep[0], "seq": link.seq[0], "sim_time": reply.telemetry.sim_time}
            line["t"] = time.time()
            out.write(json.dumps(line) + "\n")
            out.flush()

        for i, link in enumerate(links):
            link.claim()
            link.send_reset(1, seed=100 + i)
        for link in links:
            record(link)
        for _ in range(args.steps):
            actions = rng.uniform(-1, 1, (len(links), 4))
            for link, action in zip(links, actions, strict=True):
                link.send([tuple(float(a) for a in action)])
            for link in links:
                record(link)
        time.sleep(0.5)  # the side subscriber may see the last latents after the link did
        with lock:
            summary = {
                link.group: {
                    "retries": link.retries,
                    "duplicates_dropped": link.duplicates_dropped,
                    "encoders": [encoded_by.get((link.group, 1, seq), "") for seq in range(args.steps + 1)],
                }
                for link in links
            }
        out.write(json.dumps({"summary": summary}) + "\n")
    for link in links:
        link.close()
    latent_sub.undeclare()
    token.undeclare()
    session.close()


if __name__ == "__main__":
    main()
