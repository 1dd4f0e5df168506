"""`swimm up`'s port check: a live listener is refused, the TIME_WAIT leftovers of a stopped run are not."""

from __future__ import annotations

import socket

import pytest

from learner_service.up import check_port_free


def _listener() -> tuple[socket.socket, int]:
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the router's listener does
    server.bind(("127.0.0.1", 0))
    server.listen()
    return server, server.getsockname()[1]


def test_a_live_listener_is_refused() -> None:
    server, port = _listener()
    with server, pytest.raises(RuntimeError, match=f"port {port} is in use"):
        check_port_free(port)


def test_a_just_stopped_servers_time_wait_connections_do_not_block() -> None:
    server, port = _listener()
    client = socket.create_connection(("127.0.0.1", port))
    accepted, _ = server.accept()
    accepted.close()  # the side that closes first keeps the port in TIME_WAIT for a minute
    client.close()
    server.close()
    check_port_free(port)
