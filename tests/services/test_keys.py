"""Key expressions: the layout under a namespace, id validation, and parsing a step key back to (channel, group).

The Zenoh checks use zenoh.KeyExpr itself, so "valid" and "matches" mean what the router will mean.
"""

from __future__ import annotations

import re

import pytest
import zenoh

from services.keys import Keys, check_chunk

KEYS = Keys("swimm/run-1")


@pytest.mark.parametrize("value", ["0", "enc-1", "learner_ab12", "v1.2", "A-b_c.9"])
def test_plain_ids_are_accepted_unchanged(value):
    assert check_chunk(value, "env id") == value


@pytest.mark.parametrize("value", ["", "a/b", "*", "**", "enc-$1", "a b", "#1", "x?", "@live", "é"])
def test_ids_that_would_change_a_key_are_refused_naming_what_and_value(value):
    with pytest.raises(ValueError, match=re.escape(f"encoder id {value!r} may hold only letters, digits")):
        check_chunk(value, "encoder id")


def test_step_pipeline_and_control_keys():
    assert KEYS.action("train", "3") == "swimm/run-1/train/3/action"
    assert KEYS.obs("eval", "0", "enc-2") == "swimm/run-1/eval/0/obs/enc-2"
    assert KEYS.obs("train", "0", "direct") == "swimm/run-1/train/0/obs/direct"
    assert KEYS.latent("train", "3") == "swimm/run-1/train/3/latent"
    assert KEYS.ctl("eval", "1") == "swimm/run-1/eval/1/ctl"


def test_presence_and_metrics_keys():
    assert KEYS.live("encoder", "enc-2") == "swimm/run-1/@live/encoder/enc-2"
    assert KEYS.live_role("encoder") == "swimm/run-1/@live/encoder/*"
    assert KEYS.metrics("sim", "sim-1") == "swimm/run-1/metrics/sim/sim-1"
    assert KEYS.all_metrics() == "swimm/run-1/metrics/**"
    assert Keys().live("sim", "a") == "swimm/default/@live/sim/a"


def test_every_key_is_a_valid_zenoh_key_expression():
    for key in (
        KEYS.action("train", "0"),
        KEYS.obs("train", "0", "enc-1"),
        KEYS.latent("eval", "7"),
        KEYS.actions("eval"),
        KEYS.ctl("train", "0"),
        KEYS.encoder_inbox("enc-1"),
        KEYS.live("sim", "s1"),
        KEYS.live_role("sim"),
        KEYS.metrics("encoder", "enc-1"),
        KEYS.all_metrics(),
    ):
        assert str(zenoh.KeyExpr(key)) == key


def test_an_encoder_inbox_receives_only_frames_routed_to_it():
    inbox = zenoh.KeyExpr(KEYS.encoder_inbox("enc-1"))
    assert inbox.intersects(zenoh.KeyExpr(KEYS.obs("train", "0", "enc-1")))
    assert inbox.intersects(zenoh.KeyExpr(KEYS.obs("eval", "12", "enc-1")))
    assert not inbox.intersects(zenoh.KeyExpr(KEYS.obs("train", "0", "enc-2")))
    assert not inbox.intersects(zenoh.KeyExpr(KEYS.obs("train", "0", "direct")))
    assert not inbox.intersects(zenoh.KeyExpr(Keys("swimm/run-2").obs("train", "0", "enc-1")))


def test_a_role_watch_sees_its_role_only_and_metrics_never_see_tokens():
    watch = zenoh.KeyExpr(KEYS.live_role("encoder"))
    assert watch.intersects(zenoh.KeyExpr(KEYS.live("encoder", "enc-9")))
    assert not watch.intersects(zenoh.KeyExpr(KEYS.live("sim", "enc-9")))
    everything = zenoh.KeyExpr(KEYS.all_metrics())
    assert everything.intersects(zenoh.KeyExpr(KEYS.metrics("sim", "s1")))
    assert not everything.intersects(zenoh.KeyExpr(KEYS.live("sim", "s1")))


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("swimm/run-1/train/0/obs/enc-1", ("train", "0")),
        ("swimm/run-1/eval/12/action", ("eval", "12")),
        ("swimm/run-1/train/3/latent", ("train", "3")),
        ("swimm/run-1/train/learner-1.0/latent", ("train", "learner-1.0")),
    ],
)
def test_parse_step_key_returns_channel_and_group(key, expected):
    assert KEYS.parse_step_key(key) == expected


@pytest.mark.parametrize(
    "key",
    [
        "swimm/run-2/train/0/action",  # another namespace
        "swimm/run-10/train/0/action",  # a namespace that merely starts with ours
        "swimm/run-1/debug/0/action",  # not a channel
        "swimm/run-1/train/0",  # too short to be a step key
        "swimm/run-1/@live/sim/s1",
        "",
    ],
)
def test_parse_step_key_refuses_keys_outside_the_step_pipeline(key):
    with pytest.raises(ValueError, match="is not a step key of namespace 'swimm/run-1'"):
        KEYS.parse_step_key(key)


def test_a_sim_hears_every_group_of_its_channel_and_an_encoder_every_group_routed_to_it():
    actions = zenoh.KeyExpr(KEYS.actions("eval"))
    assert actions.intersects(zenoh.KeyExpr(KEYS.action("eval", "0")))  # a single env: a group of one
    assert actions.intersects(zenoh.KeyExpr(KEYS.action("eval", "learner-1.0")))
    assert not actions.intersects(zenoh.KeyExpr(KEYS.action("train", "0")))
    assert not actions.intersects(zenoh.KeyExpr(KEYS.ctl("eval", "0")))
    inbox = zenoh.KeyExpr(KEYS.encoder_inbox("enc-1"))
    assert inbox.intersects(zenoh.KeyExpr(KEYS.obs("train", "learner-1.0", "enc-1")))
    assert not inbox.intersects(zenoh.KeyExpr(KEYS.obs("train", "learner-1.0", "enc-2")))
