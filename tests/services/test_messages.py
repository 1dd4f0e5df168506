"""The message codec: every step and control message survives a round trip, and bad input becomes BadMessage with
its reason."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import numpy as np
import pytest

from services.messages import (
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    ActionMsg,
    BadMessage,
    BatchItem,
    BatchMsg,
    ClaimRequest,
    DiveMode,
    EnvState,
    InfoReply,
    InfoRequest,
    LatentMsg,
    ObservationMsg,
    Refused,
    ReleaseRequest,
    ResetReply,
    ResetRequest,
    batch_messages,
    decode_reply,
    decode_request,
    unpack,
)
from services.telemetry import Telemetry

TELEMETRY = Telemetry(
    rover_pos=(1.5, -2.25, -3.0),
    rover_quat=(0.9238795325112867, 0.0, 0.0, 0.3826834323650898),
    rover_forward=(0.7071067811865476, 0.7071067811865475, 0.0),
    rover_lin_vel=(0.25, 0.0, -0.01),
    rover_ang_vel=(0.0, 0.0, 0.1),
    target_pos=(5.0, 3.0, -3.2),
    target_quat=(1.0, 0.0, 0.0, 0.0),
    target_forward=(1.0, 0.0, 0.0),
    target_lin_vel=(0.6, 0.0, 0.0),
    target_in_frustum=True,
    collided=False,
    sim_time=12.34,
)


def _image(shape: tuple[int, int, int] = (64, 64, 3), seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=shape, dtype=np.uint8)


def _wire(message, env: str = "0") -> BatchItem:
    """``message`` as its env's item after a trip over the wire, alone in its group."""
    return BatchMsg.decode(BatchMsg.alone(BatchItem.of(env, message)).encode()).items[0]


def _observation_item(**overrides) -> BatchItem:
    """An observation's item, with fields replaced to make it bad."""
    return BatchItem("0", 1, 2, ObservationMsg("0", 1, 2, TELEMETRY, _image()).fields() | overrides)


def _action_item(**overrides) -> BatchItem:
    return BatchItem("0", 1, 2, ActionMsg(ep=1, seq=2, action=(0.0, 0.0, 0.5, -0.5)).fields() | overrides)


def _pack(body) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def _batch_payload(**overrides) -> bytes:
    return _pack({"v": PROTOCOL_VERSION, "t": 1.0, "group": "g", "items": [["0", 1, 2, {}, ""]]} | overrides)


# --- round trips -----------------------------------------------------------------------------------------------


def test_action_round_trips_every_field():
    sent = ActionMsg(
        ep=3,
        seq=417,
        action=(-1.0, 0.25, 1.0, -0.125),
        dive_mode=DiveMode.STABILISE,
        route="enc-2",
        sender="learner-ab12",
        sent_at=1700000000.5,
        prior=(-12.5,),
    )
    assert ActionMsg.from_item(_wire(sent)) == sent


def test_action_defaults_to_depth_hold_and_direct_route():
    received = ActionMsg.from_item(BatchItem("0", 0, 0, {"action": [0, 0, 1, 0]}))
    assert received.dive_mode is DiveMode.DEPTH_HOLD
    assert received.route == "direct"
    assert received.action == (0.0, 0.0, 1.0, 0.0)


def test_observation_round_trips_image_bytes_and_telemetry():
    image = _image(seed=7)
    sent = ObservationMsg(
        env="3", ep=2, seq=99, telemetry=TELEMETRY, image=image, sent_at=1700000001.25, prior=(7.5, 3.0)
    )
    received = ObservationMsg.from_item(_wire(sent, "3"), expected_shape=(64, 64, 3))
    assert (received.env, received.ep, received.seq, received.sent_at) == ("3", 2, 99, 1700000001.25)
    assert received.prior == (7.5, 3.0)
    assert received.telemetry == TELEMETRY
    assert received.image.dtype == np.uint8
    assert received.image.shape == (64, 64, 3)
    assert np.array_equal(received.image, image)


def test_observation_carries_any_hxwx3_size_when_no_shape_is_expected():
    image = _image((36, 64, 3), seed=1)
    received = ObservationMsg.from_item(_wire(ObservationMsg("0", 0, 0, TELEMETRY, image)))
    assert received.image.shape == (36, 64, 3)
    assert np.array_equal(received.image, image)


def test_observation_of_a_sim_that_does_not_render_carries_no_image():
    item = _wire(ObservationMsg("0", 1, 5, TELEMETRY, None))
    received = ObservationMsg.from_item(item)
    assert received.image is None and received.telemetry == TELEMETRY
    with pytest.raises(BadMessage, match="observation carries no image, expected \\[64, 64, 3\\]"):
        ObservationMsg.from_item(item, expected_shape=(64, 64, 3))  # what an encoder asks for


def test_latent_round_trips_every_field():
    sent = LatentMsg(
        env="1",
        ep=4,
        seq=8,
        telemetry=TELEMETRY,
        mu=(0.5, -1.25, 3.0, 0.0, 2.5, -0.75, 1.0, 0.125, 4.0, -4.0),
        logvar=(-2.0,) * 10,
        encoder="enc-1",
        sent_at=1700000002.0,
        next_prior=tuple(float(i) for i in range(64)),  # the pod tracker's whole state
    )
    assert LatentMsg.from_item(_wire(sent, "1")) == sent


def test_an_unset_prior_is_absent_from_the_wire_and_reads_back_as_none():
    messages = (
        ActionMsg(ep=1, seq=2, action=(0, 0, 0, 0)),
        ObservationMsg("0", 1, 2, TELEMETRY, None),
        LatentMsg("0", 1, 2, TELEMETRY, (0.0,), (0.0,), "enc-1"),
    )
    for message, name in zip(messages, ("prior", "prior", "next_prior"), strict=True):
        item = _wire(message)
        assert name not in item.body
        assert getattr(type(message).from_item(item), name) is None


def test_a_step_message_carries_version_and_send_time_and_each_item_its_episode_and_sequence():
    for message in (
        ActionMsg(ep=1, seq=2, action=(0, 0, 0, 0), sent_at=10.0),
        ObservationMsg("0", 1, 2, TELEMETRY, _image(), sent_at=10.0),
        LatentMsg("0", 1, 2, TELEMETRY, (0.0,), (0.0,), "enc-1", sent_at=10.0),
    ):
        body = unpack(BatchMsg("g", "s", (BatchItem.of("0", message),), sent_at=20.0).encode())
        assert (body["v"], body["t"]) == (PROTOCOL_VERSION, 20.0)
        env, ep, seq, fields, error = body["items"][0]
        assert (env, ep, seq, fields["t"], error) == ("0", 1, 2, 10.0, "")


# --- refusals: envelope ----------------------------------------------------------------------------------------


def test_malformed_msgpack_is_refused():
    with pytest.raises(BadMessage, match="malformed msgpack"):
        unpack(b"\xc1")  # 0xc1 is the one byte msgpack never uses
    with pytest.raises(BadMessage, match="malformed msgpack"):
        BatchMsg.decode(_batch_payload()[:-3])  # truncated


def test_a_payload_that_is_not_a_map_is_refused():
    with pytest.raises(BadMessage, match="must be a msgpack map"):
        unpack(_pack([PROTOCOL_VERSION, 1, 2]))


@pytest.mark.parametrize("version", [0, PROTOCOL_VERSION - 1, PROTOCOL_VERSION + 1, "1", None])
def test_unknown_protocol_version_is_refused_naming_both_versions(version):
    with pytest.raises(BadMessage, match=rf"unknown protocol version {version!r}.*speaks {PROTOCOL_VERSION}"):
        BatchMsg.decode(_batch_payload(v=version))


def test_missing_protocol_version_is_refused():
    body = {"t": 1.0, "group": "g", "items": [["0", 1, 2, {}, ""]]}
    with pytest.raises(BadMessage, match="unknown protocol version None"):
        BatchMsg.decode(_pack(body))


def test_oversized_payload_is_refused_before_decoding_with_its_size():
    payload = b"\x00" * (MAX_PAYLOAD_BYTES + 1)
    with pytest.raises(BadMessage, match=f"{MAX_PAYLOAD_BYTES + 1} bytes exceeds the {MAX_PAYLOAD_BYTES}-byte limit"):
        unpack(payload)


def test_a_large_frame_under_the_limit_is_accepted():
    image = _image((1080, 1920, 3), seed=3)  # the paper's largest frame, ~6.2 MB
    payload = BatchMsg.alone(BatchItem.of("0", ObservationMsg("0", 0, 0, TELEMETRY, image))).encode()
    assert len(payload) < MAX_PAYLOAD_BYTES
    assert np.array_equal(ObservationMsg.from_item(BatchMsg.decode(payload).items[0]).image, image)


# --- refusals: actions -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("action", "reason"),
    [
        ([0.0, 0.0, math.nan, 0.0], "NaN or infinity"),
        ([0.0, 0.0, 0.0, math.inf], "NaN or infinity"),
        ([0.0, 0.0, 1.5, 0.0], r"must lie in \[-1, 1\]"),
        ([-1.0001, 0.0, 0.0, 0.0], r"must lie in \[-1, 1\]"),
        ([0.0, 1.0], "must be 4 numbers"),
        ([0.0, 0.0, 0.0, 0.0, 0.0], "must be 4 numbers"),
        ([0.0, "fast", 0.0, 0.0], "non-number"),
        ("forward", "must be 4 numbers"),
    ],
)
def test_bad_action_is_refused(action, reason):
    with pytest.raises(BadMessage, match=reason):
        ActionMsg.from_item(_action_item(action=action))


def test_action_at_the_bounds_is_accepted():
    received = ActionMsg.from_item(_action_item(action=[-1.0, 1.0, -1.0, 1.0]))
    assert received.action == (-1.0, 1.0, -1.0, 1.0)


@pytest.mark.parametrize(("ep", "seq"), [(1, -1), (1, 1.5), (True, 2), ("3", 2), (1, None)])
def test_episode_and_sequence_must_be_non_negative_integers(ep, seq):
    with pytest.raises(BadMessage, match="item 0's ep and seq must be non-negative integers"):
        BatchMsg.decode(_batch_payload(items=[["0", ep, seq, {}, ""]]))


def test_unknown_dive_mode_is_refused():
    with pytest.raises(BadMessage, match="unknown dive_mode 'turbo'"):
        ActionMsg.from_item(_action_item(dive_mode="turbo"))


def test_non_string_route_is_refused():
    with pytest.raises(BadMessage, match="field 'route' must be a string"):
        ActionMsg.from_item(_action_item(route=7))


@pytest.mark.parametrize("sent_at", ["yesterday", None])
def test_bad_send_time_is_refused_as_bad_message(sent_at):
    with pytest.raises(BadMessage, match="'t'"):
        ActionMsg.from_item(_action_item(t=sent_at))


# --- refusals: images and telemetry ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "reason"),
    [
        ({"dtype": "float32"}, "image dtype must be uint8, got 'float32'"),
        ({"shape": [64, 64, 4]}, r"image shape must be \[H, W, 3\]"),
        ({"shape": [64, 64]}, r"image shape must be \[H, W, 3\]"),
        ({"shape": [0, 64, 3]}, r"image shape must be \[H, W, 3\]"),
        ({"shape": "64x64x3"}, r"image shape must be \[H, W, 3\]"),
        ({"shape": [32, 64, 3]}, r"image bytes do not match shape \[32, 64, 3\]"),
        ({"image": b"\x00" * 100}, r"image bytes do not match shape \[64, 64, 3\]"),
        ({"image": "pixels"}, r"image bytes do not match shape"),
    ],
)
def test_bad_image_is_refused(overrides, reason):
    with pytest.raises(BadMessage, match=reason):
        ObservationMsg.from_item(_observation_item(**overrides))


def test_image_of_an_unexpected_size_is_refused_naming_both_shapes():
    item = _wire(ObservationMsg("0", 0, 0, TELEMETRY, _image((128, 128, 3))))
    with pytest.raises(BadMessage, match=r"image shape \[128, 128, 3\] differs from the expected \[64, 64, 3\]"):
        ObservationMsg.from_item(item, expected_shape=(64, 64, 3))


def test_observation_without_telemetry_field_is_refused_naming_it():
    telemetry = TELEMETRY.to_dict()
    del telemetry["target_pos"]
    with pytest.raises(BadMessage, match="telemetry lacks field 'target_pos'"):
        ObservationMsg.from_item(_observation_item(telemetry=telemetry))


def test_observation_with_malformed_telemetry_is_refused():
    with pytest.raises(BadMessage, match="'telemetry' must be a map"):
        ObservationMsg.from_item(_observation_item(telemetry=[1, 2, 3]))
    bad_quat = {**TELEMETRY.to_dict(), "rover_quat": [1.0, 0.0, 0.0]}
    with pytest.raises(BadMessage, match="'rover_quat' must have 4 numbers"):
        ObservationMsg.from_item(_observation_item(telemetry=bad_quat))


def test_a_pods_identity_ground_truth_round_trips_and_a_fractional_dolphin_is_refused():
    pod = dataclasses.replace(TELEMETRY, pod_size=4, followed=2, target_occluded=True)
    assert ObservationMsg.from_item(_wire(ObservationMsg("0", 1, 2, pod, None))).telemetry == pod
    for followed in (1.5, True, "2"):
        telemetry = {**pod.to_dict(), "followed": followed}
        with pytest.raises(BadMessage, match="telemetry field 'followed' must be an integer"):
            ObservationMsg.from_item(_observation_item(telemetry=telemetry))


def test_latent_with_mismatched_logvar_or_nan_mean_is_refused():
    fields = LatentMsg("0", 0, 0, TELEMETRY, (0.0, 1.0), (0.0, 0.0), "enc-1").fields()
    with pytest.raises(BadMessage, match="field 'logvar' must be 2 numbers"):
        LatentMsg.from_item(BatchItem("0", 0, 0, fields | {"logvar": [0.0, 0.0, 0.0]}))
    with pytest.raises(BadMessage, match="field 'mu' holds NaN or infinity"):
        LatentMsg.from_item(BatchItem("0", 0, 0, fields | {"mu": [math.nan, 0.0]}))


@pytest.mark.parametrize(
    "prior, reason",
    [("left", "must be a list of 1 to 256 numbers"), (1.0, "must be a list of 1 to 256 numbers"),
     ([], "must be a list of 1 to 256 numbers"), ([0.0] * 257, "must be a list of 1 to 256 numbers"),
     ([True], "holds a non-number"), (["left"], "holds a non-number"), ([1.0, math.nan], "holds NaN or infinity"),
     ([math.inf], "holds NaN or infinity")],
)  # fmt: skip
def test_a_prior_that_is_not_a_list_of_finite_numbers_is_refused_naming_its_field(prior, reason):
    latent = LatentMsg("0", 0, 0, TELEMETRY, (0.0,), (0.0,), "enc-1").fields()
    for read, fields, name in (
        (ActionMsg.from_item, _action_item().body, "prior"),
        (ObservationMsg.from_item, _observation_item().body, "prior"),
        (LatentMsg.from_item, latent, "next_prior"),
    ):
        with pytest.raises(BadMessage, match=f"field '{name}' {reason}"):
            read(BatchItem("0", 1, 2, fields | {name: prior}))


def test_a_batch_round_trips_its_items_fields_errors_and_addressee():
    action = ActionMsg(ep=3, seq=7, action=(0.0, 0.1, 0.5, -0.25), route="enc-1", sender="learner-x")
    items = (BatchItem.of("0", action), BatchItem("1", 2, 9, error="held"))
    batch = BatchMsg("learner-x.0", "sim-1", items, to="learner-x")
    decoded = BatchMsg.decode(batch.encode())
    assert decoded == batch
    assert ActionMsg.from_item(decoded.items[0]) == action
    assert [(env, msg.seq) for env, msg in batch_messages(batch.encode(), ActionMsg.from_item)] == [("0", 7)]


def test_a_single_env_travels_as_a_group_of_one_named_after_it():
    action = ActionMsg(ep=1, seq=2, action=(0.0, 0.0, 0.5, 0.0), sender="learner-x")
    alone = BatchMsg.decode(BatchMsg.alone(BatchItem.of("4", action), "learner-x").encode())
    assert (alone.group, alone.sender, alone.to) == ("4", "learner-x", "")
    assert alone.items == (BatchItem("4", 1, 2, action.fields()),)


@pytest.mark.parametrize(
    ("items", "reason"),
    [
        ([], "non-empty list"),
        ("0", "non-empty list"),
        ([["0", 1, 2, {}]], r"item 0 must be \[env, ep, seq, fields, error\]"),
        ([["0", -1, 2, {}, ""]], "item 0's ep and seq must be non-negative integers"),
        ([["0", 1, 2, b"packed", ""]], "item 0's fields must be a map, got bytes"),
        ([["0", 1, 2, {}, 5]], "item 0's env and error must be strings"),
        ([[7, 1, 2, {}, ""]], "item 0's env and error must be strings"),
    ],
)
def test_a_bad_batch_is_refused_naming_what_is_wrong(items, reason):
    with pytest.raises(BadMessage, match=reason):
        BatchMsg.decode(_batch_payload(items=items))


# --- the control plane -----------------------------------------------------------------------------------------

CONTROL_REQUESTS = [
    InfoRequest(),
    ClaimRequest("learner-1"),
    ReleaseRequest("learner-1"),
    ResetRequest("learner-1", ep=3, seed=42),
    ResetRequest("learner-1", 4, 7, "enc-1", noise={"preset": "murky"}, latency={"camera_ms": 40}, scene={"a": 1}),
    ResetRequest("learner-1", 5, 8, noise=False),
]


@pytest.mark.parametrize("request_", CONTROL_REQUESTS, ids=repr)
def test_every_control_request_round_trips_as_its_own_type(request_):
    assert decode_request(request_.encode()) == request_
    body = unpack(request_.encode())
    assert (body["v"], body["op"]) == (PROTOCOL_VERSION, request_.OP) and body["t"] > 1.6e9


@pytest.mark.parametrize(
    "reply",
    [
        EnvState("train", "0", "learner-1", ep=3, seq=0),
        EnvState("eval", "2", None, ep=0, seq=0),  # free
        InfoReply("eval", "2", None, ep=1, seq=9, sim="sim-1", image_size=64),
        ResetReply("train", "0", "learner-1", ep=3, seq=0, replayed=True),
    ],
    ids=repr,
)
def test_every_control_reply_round_trips_as_the_type_its_request_expects(reply):
    assert decode_reply(reply.encode(), type(reply)) == reply


def test_a_refusal_round_trips_whatever_reply_was_expected():
    assert decode_reply(Refused("env train/0 is held by learner-2").encode(), ResetReply) == Refused(
        "env train/0 is held by learner-2"
    )


def test_each_request_names_the_reply_it_gets():
    assert InfoRequest.REPLY is InfoReply and ResetRequest.REPLY is ResetReply
    assert ClaimRequest.REPLY is EnvState and ReleaseRequest.REPLY is EnvState


def _control(**fields) -> bytes:
    return _pack({"v": PROTOCOL_VERSION, "t": 0.0, **fields})


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (_control(), "field 'op' must be a string, got None"),
        (_control(op=1), "field 'op' must be a string, got 1"),
        (_control(op="seed"), "unknown control op 'seed' \\(known: info, claim, release, reset\\)"),
        (_control(op="claim"), "field 'holder' must be a string, got None"),
        (_control(op="release", holder=7), "field 'holder' must be a string, got 7"),
        (_control(op="reset", holder="l", seed=1), "field 'ep' must be a non-negative integer, got None"),
        (_control(op="reset", holder="l", ep=1, seed=-1), "field 'seed' must be a non-negative integer, got -1"),
        (_control(op="reset", holder="l", ep=True, seed=1), "field 'ep' must be a non-negative integer, got True"),
        (_control(op="reset", holder="l", ep=1, seed=1, route=3), "field 'route' must be a string, got 3"),
        (_control(op="reset", holder="l", ep=1, seed=1, noise="maybe"), "field 'noise' must be true, false, a map"),
        (_control(op="reset", holder="l", ep=1, seed=1, latency=True), "field 'latency' must be a map or absent"),
        (_control(op="reset", holder="l", ep=1, seed=1, scene=[1]), "field 'scene' must be a map or absent"),
        (_pack({"v": PROTOCOL_VERSION + 1, "op": "info"}), f"unknown protocol version {PROTOCOL_VERSION + 1}"),
        (b"\xc1", "malformed msgpack"),
    ],
)
def test_a_bad_control_request_is_refused_naming_what_is_wrong(payload, reason):
    with pytest.raises(BadMessage, match=reason):
        decode_request(payload)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (_control(channel="train", env="0", holder=None, ep=0, seq=0), "field 'ok' must be true or false, got None"),
        (_control(ok=False), "field 'error' must be a string, got None"),
        (_control(ok=True, channel="train", env="0", holder=None, ep=0), "field 'seq' must be a non-negative"),
        (_control(ok=True, channel="train", env="0", holder=3, ep=0, seq=0), "field 'holder' must be a string"),
        (_control(ok=True, channel="eval", env="0", holder=None, ep=0, seq=0, sim="s"), "field 'image_size'"),
    ],
)
def test_a_bad_control_reply_is_refused_naming_what_is_wrong(payload, reason):
    with pytest.raises(BadMessage, match=reason):
        decode_reply(payload, InfoReply)
