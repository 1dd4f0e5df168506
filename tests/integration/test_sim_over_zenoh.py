"""`swimm router` + `swimm sim` as real processes: determinism, router restart, bad input, real-time mode,
SIGTERM."""

from __future__ import annotations

import math
import queue
import time

import msgpack
import numpy as np
import pytest
import zenoh

from learner_service.link import StepRefused
from services import control
from services.low_latency import largest_low_latency_image_size
from services.messages import (
    DIRECT_ROUTE,
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    ActionMsg,
    BatchItem,
    BatchMsg,
    EnvState,
    InfoRequest,
    ObservationMsg,
    Refused,
    batch_messages,
    decode_reply,
)
from services.procs import free_tcp_port, wait_for_port
from sim_service.settings import WorldSettings
from sim_service.world import World
from tests.integration.conftest import start_sim

pytestmark = pytest.mark.slow


def actions(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [tuple(float(x) for x in row) for row in rng.uniform(-1, 1, (n, 4))]


def inprocess_episode(seed: int, steps):
    world = World()
    try:
        frames = [world.reset(seed)] + [world.step(a) for a in steps]
        return [(t, image.tobytes()) for t, image in frames]
    finally:
        world.close()


def remote_episode(link, ep: int, seed: int, steps):
    link.send_reset(ep, seed)
    replies = link.wait()
    for action in steps:
        link.send([action])
        replies += link.wait()
    return [(r.telemetry, r.image.tobytes()) for r in replies]


@pytest.mark.parametrize("poll_ms", [0.0, 2.0], ids=["blocking", "polling"])
def test_same_seed_gives_identical_bytes_inprocess_and_over_zenoh_twice(group, connect_client, namespace, poll_ms):
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--poll-ms", str(poll_ms))
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    published: queue.Queue[dict] = queue.Queue()
    client.session.declare_subscriber(
        client.keys.metrics("sim", "*"), lambda sample: published.put(msgpack.unpackb(sample.payload.to_bytes()))
    )
    link = client.link(poll_ms=poll_ms)
    link.claim()
    steps = actions(150)
    expected = inprocess_episode(42, steps)
    assert remote_episode(link, 1, 42, steps) == expected
    assert remote_episode(link, 2, 42, steps) == expected  # a second episode with the same seed
    link.close()
    # ...though the sim prepared steps ahead while it waited for actions (World.prepare_step).
    metrics = published.get(timeout=10)
    while metrics.get("steps", 0) < 2 * len(steps):
        metrics = published.get(timeout=10)
    assert 0 < metrics["steps_prepared"] <= metrics["steps"] + metrics.get("ctl_reset", 0)


@pytest.mark.parametrize("mode", ["peer", "client"])
def test_low_latency_links_step_identically_up_to_the_largest_image_they_carry(group, connect_client, namespace, mode):
    """A low-latency sim and learner (as peers linked directly, or as clients of a low-latency router) give the
    in-process bytes; and the largest image a sim accepts with --low-latency (check_fits_low_latency) does cross
    such links, which a message over the transport's limit would not."""
    endpoint = group.start_router(flags=("--low-latency",))
    low_latency_sim = ("--mode", mode, "--low-latency", "--poll-ms", "2")
    start_sim(group, endpoint, namespace, *low_latency_sim, "--eval-envs", "0")
    largest = largest_low_latency_image_size()
    start_sim(group, endpoint, namespace, *low_latency_sim, "--train-envs", "0", "--image-size", str(largest),
              name="sim-large")  # fmt: skip
    client = connect_client(endpoint, mode=mode, low_latency=True)
    client.roster("sim").wait_for(2, timeout_s=60)
    link = client.link(poll_ms=2.0)
    link.claim()
    steps = actions(60)
    assert remote_episode(link, 1, 42, steps) == inprocess_episode(42, steps)
    link.close()

    large = client.link("eval", poll_ms=2.0)
    large.claim()
    large.send_reset(1, 7)
    assert large.wait()[0].image.shape == (largest, largest, 3)
    large.send([(0, 0, 0.5, 0)])
    assert large.wait()[0].image.shape == (largest, largest, 3)
    large.close()


@pytest.mark.parametrize("transport", ["standard", "low-latency"])
def test_router_restart_mid_run_loses_and_repeats_no_step(group, connect_client, namespace, tmp_path, transport):
    flags = ("--low-latency",) if transport == "low-latency" else ()  # router, sim and client alike
    port = free_tcp_port()
    endpoint = group.start_router(port, flags=flags)
    router = group.services[-1]
    start_sim(group, endpoint, namespace, *flags)
    client = connect_client(endpoint, low_latency=bool(flags))
    client.roster("sim").wait_for(1, timeout_s=60)
    link = client.link(step_timeout_s=0.5, max_retries=40)
    link.claim()
    steps = actions(200, seed=7)
    expected = inprocess_episode(9, steps)

    link.send_reset(1, 9)
    replies = link.wait()
    outage = None
    for i, action in enumerate(steps):
        if i == 100:  # kill the router mid-episode and bring it back on the same endpoint
            group.stop(router, kill=True)
            killed_at = time.monotonic()
            group.start("router-2", "router", "--listen", endpoint, *flags)
            assert wait_for_port("127.0.0.1", port, timeout_s=20)
        link.send([action])
        replies += link.wait()
        if i == 100:
            outage = time.monotonic() - killed_at
    got = [(r.telemetry, r.image.tobytes()) for r in replies]
    assert got == expected  # every step applied exactly once, in order
    assert link.retries >= 1  # the outage was real and bridged by re-sends
    assert outage is not None and outage < 10.0  # documented bound: resume within 10 s
    (tmp_path / "outage.txt").write_text(f"{outage:.2f}")


def test_bad_control_requests_are_refused_naming_what_was_wrong_and_the_sim_keeps_serving(
    group, connect_client, namespace
):
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace)
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    ctl = client.keys.ctl("train", "0")

    def answer(payload: bytes) -> EnvState | Refused:
        (reply,) = client.session.get(ctl, payload=payload, timeout=10)
        return decode_reply(reply.ok.payload.to_bytes(), EnvState)

    def refusal(**fields) -> str:
        """The sim's reason for refusing a control request of these fields (the version unless ``v`` is given)."""
        refused = answer(msgpack.packb({"v": PROTOCOL_VERSION, "t": 0.0, **fields}))
        assert isinstance(refused, Refused), refused
        return refused.reason

    holder = client.holder
    assert refusal(op="seed", seed=41) == "unknown control op 'seed' (known: info, claim, release, reset)"
    assert refusal(holder=holder) == "field 'op' must be a string, got None"
    assert refusal(op="claim") == "field 'holder' must be a string, got None"
    assert refusal(op="claim", holder=7) == "field 'holder' must be a string, got 7"
    assert refusal(op="reset", holder=holder, ep=1) == "field 'seed' must be a non-negative integer, got None"
    assert refusal(op="reset", holder=holder, ep="1", seed=3).startswith("field 'ep' must be a non-negative integer")
    assert refusal(op="info", v=PROTOCOL_VERSION + 1).startswith(f"unknown protocol version {PROTOCOL_VERSION + 1}")
    assert "not claimed" in refusal(op="reset", holder=holder, ep=1, seed=3)
    assert refusal(op="release", holder=holder) == f"env train/0 is not held by {holder} (holder: None)"
    # The typed requests are granted, each answered with the env's state.
    link = client.link()
    assert link.claim() == EnvState("train", "0", holder, ep=0, seq=0)
    other = connect_client(endpoint)
    assert "held by " + holder in refusal(op="claim", holder=other.holder)
    link.send_reset(1, 3)
    link.wait()
    (info,) = control.survey(client.session, ctl)
    assert (info.holder, info.ep, info.seq, info.image_size) == (holder, 1, 0, WorldSettings().image_size)
    link.close()
    assert control.request(client.session, ctl, InfoRequest()).holder is None  # released
    assert group.services[1].alive


@pytest.mark.parametrize("poll_ms", [0.0, 2.0], ids=["blocking", "polling"])
def test_bad_input_is_refused_with_a_reason_and_the_sim_keeps_serving(group, connect_client, namespace, poll_ms):
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--poll-ms", str(poll_ms))
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    keys = client.keys
    answers: queue.Queue[BatchItem] = queue.Queue()
    sub = client.session.declare_subscriber(
        keys.obs("train", "0", DIRECT_ROUTE), lambda s: answers.put(BatchMsg.decode(s.payload.to_bytes()).items[0])
    )

    def send(payload: bytes) -> None:
        # BLOCK: a put drops under congestion by default, and an 8 MB payload goes out in many fragments
        client.session.put(keys.action("train", "0"), payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def refused(action: dict, seq: int = 1) -> str:
        """The sim's reason for refusing ``action`` (its fields) as env 0's step (1, seq): the error item answering
        it."""
        send(BatchMsg.alone(BatchItem("0", 1, seq, action), sender=client.holder).encode())
        answer = answers.get(timeout=10)
        assert (answer.env, answer.ep, answer.seq, answer.body) == ("0", 1, seq, {}), answer
        return answer.error

    def action_body(**overrides) -> dict:
        return ActionMsg(1, 1, (0, 0, 0, 0), sender=client.holder, sent_at=0.0).fields() | overrides

    # Before any claim: the env refuses to be driven and says so.
    assert "not claimed" in refused(action_body())
    link = client.link(poll_ms=poll_ms)
    link.claim()
    link.send_reset(1, 3)
    link.wait()
    answers.get(timeout=10)  # the reset's observation
    assert "action" in refused(action_body(action=[0, 0, 0])).lower()
    assert "nan" in refused(action_body(action=[0, 0, math.nan, 0])).lower()
    assert "[-1, 1]" in refused(action_body(action=[0, 0, 3.0, 0]))
    assert "dive" in refused(action_body(dive_mode="warp")).lower()
    assert "out of order" in refused(action_body(), seq=5)
    # A message no env's item can be read from has no one to answer: it is counted and logged, and dropped.
    another_version = msgpack.packb({"v": 99, "group": "0", "items": [["0", 1, 1, action_body(), ""]]})
    not_a_batch = msgpack.packb({"v": PROTOCOL_VERSION, "ep": 1, "seq": 1, **action_body()})
    for unreadable in (b"\xc1\xff not msgpack", b"\x00" * (MAX_PAYLOAD_BYTES + 1), another_version, not_a_batch):
        send(unreadable)
    with pytest.raises(queue.Empty):
        answers.get(timeout=1.0)

    # A second learner is refused by name; the first keeps stepping as if nothing happened.
    other = connect_client(endpoint)
    with pytest.raises(Exception, match="held by"):
        other.link().claim()
    # The refusals above name the step they answer, so the link would take them as its own for (1, 1): a new
    # episode leaves them behind.
    link.send_reset(2, 3)
    link.wait()
    # A refusal of somebody else's step is not taken for one of the link's own: ``to`` names whom it answers.
    spoof = ActionMsg(2, 1, (0, 0, 0, 0), sender=other.holder)
    send(BatchMsg.alone(BatchItem.of("0", spoof), other.holder).encode())
    link.send([(0, 0, 0.5, 0.1)])
    link.wait()
    assert (link.ep, link.seq) == ([2], [1])
    # The link hears its own refusals (blocking or polling) and raises them with the sim's reason.
    link.send([(0, 0, 3.0, 0)])
    with pytest.raises(StepRefused, match=r"\[-1, 1\]"):
        link.wait()
    sub.undeclare()
    link.close()
    assert group.services[1].alive


def test_the_sim_echoes_each_actions_prior_into_its_observation_a_retrys_too(group, connect_client, namespace):
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace)
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    answers: queue.Queue[BatchItem] = queue.Queue()
    key = client.keys.obs("train", "0", DIRECT_ROUTE)
    sub = client.session.declare_subscriber(key, lambda s: answers.put(BatchMsg.decode(s.payload.to_bytes()).items[0]))
    link = client.link()
    link.claim()
    link.send_reset(1, 3)
    link.wait()
    assert ObservationMsg.from_item(answers.get(timeout=10)).prior is None  # a reset's target: the image centre

    def answer(seq: int, prior) -> BatchItem:
        """The sim's answer to env 0's step (1, seq) carrying ``prior``."""
        action = ActionMsg(1, seq, (0, 0, 0.5, 0), sender=client.holder).fields() | {"prior": prior}
        client.session.put(client.keys.action("train", "0"), BatchMsg.alone(BatchItem("0", 1, seq, action)).encode())
        return answers.get(timeout=10)

    assert ObservationMsg.from_item(answer(1, [12.5, 6.0])).prior == (12.5, 6.0)
    assert ObservationMsg.from_item(answer(1, [-4.0])).prior == (-4.0,)  # a retry, answered from the cache
    assert "field 'prior' must be a list of 1 to 256 numbers" in answer(2, "left").error
    sub.undeclare()
    link.close()


def forward_speed(telemetry) -> float:
    return float(np.dot(telemetry.rover_lin_vel, telemetry.rover_forward))


@pytest.mark.parametrize("poll_ms", [0.0, 2.0], ids=["blocking", "polling"])
def test_a_realtime_sim_steps_on_its_clock_holding_the_latest_action(group, connect_client, namespace, poll_ms):
    dt = WorldSettings().physics_dt
    endpoint = group.start_router()
    start_sim(group, endpoint, namespace, "--realtime", "--poll-ms", str(poll_ms))
    client = connect_client(endpoint)
    client.roster("sim").wait_for(1, timeout_s=60)
    received: queue.Queue[tuple[float, ObservationMsg]] = queue.Queue()
    sub = client.session.declare_subscriber(
        client.keys.obs("train", "0", DIRECT_ROUTE),
        lambda s: [
            received.put((time.perf_counter(), obs))
            for _, obs in batch_messages(s.payload.to_bytes(), ObservationMsg.from_item)
        ],  # fmt: skip
    )
    link = client.link()
    link.claim()
    link.send_reset(1, 5)
    link.wait()

    def observe(seconds: float) -> list[tuple[float, ObservationMsg]]:
        end, got = time.perf_counter() + seconds, []
        while (left := end - time.perf_counter()) > 0:
            try:
                got.append(received.get(timeout=left))
            except queue.Empty:
                break
        return [(t, obs) for t, obs in got if obs.seq > 0]  # the reset's own observation is seq 0

    idle = observe(1.0)  # no action sent: the sim steps anyway, holding the zero action
    seqs = [obs.seq for _, obs in idle]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "a tick was skipped or repeated"
    assert 0.5 / dt <= len(idle) <= 1.5 / dt
    assert np.median(np.diff([t for t, _ in idle])) == pytest.approx(dt, rel=0.5)
    assert np.allclose(np.diff([obs.telemetry.sim_time for _, obs in idle]), dt)
    assert abs(forward_speed(idle[-1][1].telemetry)) < 0.05

    # One action, any seq: applied at the next tick and held until another comes.
    surge = ActionMsg(ep=1, seq=1, action=(0.0, 0.0, 1.0, 0.0), sender=client.holder)
    client.session.put(
        client.keys.action("train", "0"), BatchMsg.alone(BatchItem.of("0", surge), client.holder).encode()
    )
    surging = observe(2.0)
    speeds = [forward_speed(obs.telemetry) for _, obs in surging]
    assert speeds[-1] > 0.3 and speeds[-1] > speeds[len(speeds) // 2] > speeds[0]
    sub.undeclare()
    link.close()


def test_sigterm_stops_a_serving_sim_cleanly_and_it_leaves_the_roster(group, connect_client, namespace):
    endpoint = group.start_router()
    sim = start_sim(group, endpoint, namespace)
    client = connect_client(endpoint)
    sims = client.roster("sim")
    sims.wait_for(1, timeout_s=60)
    link = client.link()
    link.claim()
    link.send_reset(1, 3)
    link.wait()
    link.send([(0.0, 0.0, 0.5, 0.0)])
    link.wait()
    assert link.seq == [1]
    assert group.stop(sim, timeout_s=10) == 0, sim.log_tail()  # not killed after the 10 s
    assert "stopped: {" in sim.log_tail(), sim.log_tail()  # its last words: the metrics it served
    deadline = time.monotonic() + 5
    while sims.members() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not sims.members()
