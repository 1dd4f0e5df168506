"""Every Zenoh config shipped in deploy/zenoh/ is one Zenoh itself accepts, in the mode its name promises."""

from __future__ import annotations

import json

import pytest
import zenoh

from tests.deploy.secure_zenoh import ZENOH_DIR

CONFIGS = sorted(ZENOH_DIR.glob("*.json5"))


def test_there_are_router_and_client_configs():
    names = {path.name for path in CONFIGS}
    assert {"router-tls-acl.json5", "router-site.json5", "client-lan.json5"} <= names
    assert {f"client-tls-{role}.json5" for role in ("learner", "eval", "sim", "encoder")} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_zenoh_parses_the_config_in_the_mode_its_name_says(path):
    config = zenoh.Config.from_file(str(path))
    expected = "router" if path.name.startswith("router") else "client"
    assert json.loads(config.get_json("mode")) == expected
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False  # endpoints only, no discovery


def test_every_role_in_the_example_credentials_has_a_client_config():
    users = [line.split(":", 1)[0] for line in (ZENOH_DIR / "credentials.example.txt").read_text().split()]
    for user in users:
        config = zenoh.Config.from_file(str(ZENOH_DIR / f"client-tls-{user}.json5"))
        assert json.loads(config.get_json("transport/auth/usrpwd/user")) == user
