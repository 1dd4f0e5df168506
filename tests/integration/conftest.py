"""Fixtures for tests across real processes: a router, services, and a learner-side client session."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import zenoh

from learner_service.link import EnvLink, new_holder_id
from services.keys import Keys
from services.presence import Roster, announce
from services.procs import ProcessGroup
from services.session import open_session
from services.settings import ZenohSettings


@pytest.fixture
def group(processes: ProcessGroup) -> ProcessGroup:
    """The test's process group (tests/conftest.py's ``processes``), under the name these tests use."""
    return processes


@dataclass
class Client:
    """A learner-side Zenoh session with a liveliness token, as `swimm learn` has."""

    session: zenoh.Session
    keys: Keys
    holder: str
    token: zenoh.LivelinessToken

    def link(self, channel: str = "train", env: str = "0", encoders: Roster | None = None, **kwargs) -> EnvLink:
        """A link of one env (a group of one); ``envs=[...]`` and ``group=...`` in ``kwargs`` make a group."""
        return EnvLink(
            self.session,
            self.keys,
            channel,
            kwargs.pop("envs", [env]),
            self.holder,
            encoded=encoders is not None,
            encoders=encoders,
            **kwargs,
        )

    def roster(self, role: str) -> Roster:
        return Roster(self.session, self.keys, role)


@pytest.fixture
def connect_client(namespace):
    """Factory: a Client connected to an endpoint; closed at teardown."""
    opened: list[Client] = []

    def connect(endpoint: str, mode: str = "client", low_latency: bool = False) -> Client:
        settings = ZenohSettings(mode=mode, connect=[endpoint], namespace=namespace, low_latency=low_latency)
        session = open_session(settings, role="test")
        keys = Keys(namespace)
        holder = new_holder_id("learner")
        client = Client(session, keys, holder, announce(session, keys, "learner", holder))
        opened.append(client)
        return client

    yield connect
    for client in opened:
        client.token.undeclare()
        client.session.close()


def start_sim(group: ProcessGroup, endpoint: str, namespace: str, *args: str, name: str = "sim"):
    return group.start(name, "sim", "--connect", endpoint, "--namespace", namespace, *args)


def start_encoders(group: ProcessGroup, endpoint: str, namespace: str, checkpoint, idents, *args: str) -> dict:
    """One `swimm encoder` process on ``checkpoint`` per ident, one thread each, keyed by ident."""
    common = ("--connect", endpoint, "--namespace", namespace, "--checkpoint", str(checkpoint), "--threads", "1")
    return {ident: group.start(ident, "encoder", *args, *common, "--ident", ident) for ident in idents}
