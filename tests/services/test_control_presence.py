"""Control request/reply and liveliness presence between Zenoh client sessions through a real `swimm router` process."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable

import pytest
import zenoh

from services import control
from services.control import ControlError
from services.keys import Keys
from services.messages import (
    AnyControlRequest,
    ClaimRequest,
    EnvState,
    InfoReply,
    InfoRequest,
    Refused,
    ResetRequest,
    decode_request,
)
from services.presence import Roster, announce, live_now

#: Presence changes cross two hops (client -> router -> client); they must show within this bound.
VISIBLE_WITHIN_S = 5.0


def wait_until(condition: Callable[[], bool], timeout_s: float = VISIBLE_WITHIN_S) -> float:
    """Poll until ``condition()`` holds; return the seconds it took, or fail the test naming the bound."""
    start = time.monotonic()
    while not condition():
        if time.monotonic() - start > timeout_s:
            pytest.fail(f"condition not met within {timeout_s} s")
        time.sleep(0.02)
    return time.monotonic() - start


def serve_ctl(
    session: zenoh.Session, key: str, answer: Callable[[AnyControlRequest], EnvState | Refused]
) -> zenoh.Queryable:
    """A queryable answering each control request with ``answer(request)``; keep the result referenced."""

    def on_query(query: zenoh.Query) -> None:
        control.reply(query, answer(decode_request(query.payload.to_bytes())))

    return session.declare_queryable(key, on_query)


@pytest.fixture
def keys(namespace) -> Keys:
    return Keys(namespace)


def test_request_gets_the_responders_typed_reply_to_the_typed_request(zenoh_router, zenoh_session, keys):
    sim, learner = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    key = keys.ctl("train", "0")
    heard: list[AnyControlRequest] = []

    def claim(request: AnyControlRequest) -> EnvState:
        heard.append(request)
        return EnvState("train", "0", request.holder, ep=4, seq=0)

    _queryable = serve_ctl(sim, key, claim)
    reply = control.request(learner, key, ClaimRequest("learner-1"), timeout_s=5.0)
    assert heard == [ClaimRequest("learner-1")]
    assert reply == EnvState("train", "0", "learner-1", ep=4, seq=0)


def test_refusal_raises_with_the_responders_reason(zenoh_router, zenoh_session, keys):
    sim, learner = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    key = keys.ctl("train", "0")
    _queryable = serve_ctl(sim, key, lambda request: Refused(f"held by learner-2, not {request.holder}"))

    with pytest.raises(ControlError, match="claim on .*/train/0/ctl refused: held by learner-2, not learner-1"):
        control.request(learner, key, ClaimRequest("learner-1"))


def test_unanswered_request_times_out_retryably_naming_the_key(zenoh_router, zenoh_session, keys):
    learner = zenoh_session(zenoh_router)
    started = time.monotonic()
    with pytest.raises(control.ControlTimeout, match=r"info on .*/eval/9/ctl: no reply within 0.5 s"):
        control.request(learner, keys.ctl("eval", "9"), InfoRequest(), timeout_s=0.5)
    assert time.monotonic() - started < 3.0


def test_a_responder_slower_than_the_timeout_times_out_retryably(zenoh_router, zenoh_session, keys):
    """Zenoh answers a query whose timeout passed with an error reply; that is a timeout, not a refusal."""
    sim, learner = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    key = keys.ctl("train", "0")

    def slow(query: zenoh.Query) -> None:
        time.sleep(1.5)
        control.reply(query, EnvState("train", "0", None, ep=0, seq=0))

    _queryable = sim.declare_queryable(key, slow)
    with pytest.raises(control.ControlTimeout, match="reset on .*/train/0/ctl: no reply within 0.5 s"):
        control.request(learner, key, ResetRequest("learner-1", ep=1, seed=1), timeout_s=0.5)


def test_unreadable_reply_is_reported_not_raised_raw(zenoh_router, zenoh_session, keys):
    sim, learner = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    key = keys.ctl("train", "0")

    def garbage(query: zenoh.Query) -> None:
        query.reply(query.key_expr, b"\xc1")
        query.drop()

    _queryable = sim.declare_queryable(key, garbage)
    with pytest.raises(ControlError, match="info on .*: unreadable reply \\(malformed msgpack"):
        control.request(learner, key, InfoRequest())


def test_survey_collects_info_from_every_env_and_skips_refusals(zenoh_router, zenoh_session, keys):
    sim, learner = zenoh_session(zenoh_router), zenoh_session(zenoh_router)

    def info(env: str) -> Callable[[AnyControlRequest], EnvState | Refused]:
        """Env ``env``'s info, answered to an info request only."""
        return lambda request: (
            InfoReply("eval", env, None, ep=0, seq=0, sim="sim-1", image_size=64)
            if isinstance(request, InfoRequest)
            else Refused(f"not an info request: {request}")
        )

    _queryables = [serve_ctl(sim, keys.ctl("eval", env), info(env)) for env in ("0", "1", "2")]
    _refuser = serve_ctl(sim, keys.ctl("train", "0"), lambda request: Refused("busy"))

    def survey() -> list[InfoReply]:
        return control.survey(learner, f"{keys.namespace}/*/*/ctl", timeout_s=1.0)

    wait_until(lambda: len(survey()) >= 3)  # the queryables reach the learner through the router a moment later
    assert sorted(info.env for info in survey()) == ["0", "1", "2"]


def test_roster_sees_a_service_join_and_leave_within_the_bound(zenoh_router, zenoh_session, keys):
    watcher, encoder = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    changes: list[tuple[set[str], set[str]]] = []
    roster = Roster(watcher, keys, "encoder", on_change=lambda joined, left: changes.append((joined, left)))
    assert roster.members() == set()

    token = announce(encoder, keys, "encoder", "enc-1")
    started = time.monotonic()
    assert roster.wait_for(1, timeout_s=VISIBLE_WITHIN_S) == {"enc-1"}
    assert time.monotonic() - started < VISIBLE_WITHIN_S

    token.undeclare()
    wait_until(lambda: roster.members() == set())
    wait_until(lambda: len(changes) == 2)  # on_change runs just after the members change, on Zenoh's thread
    assert changes == [({"enc-1"}, set()), (set(), {"enc-1"})]
    roster.close()


def test_live_now_asks_the_network_afresh_for_one_roles_tokens(zenoh_router, zenoh_session, keys):
    asker, services = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    learner = announce(services, keys, "learner", "learner-1")
    sim = announce(services, keys, "sim", "sim-1")
    wait_until(lambda: live_now(asker, keys, "learner") == {"learner-1"})
    learner.undeclare()
    wait_until(lambda: live_now(asker, keys, "learner") == set())
    assert live_now(asker, keys, "sim") == {"sim-1"}
    sim.undeclare()


def test_a_departure_is_reported_even_when_its_arrival_was_not_seen(zenoh_router, zenoh_session, keys):
    services = zenoh_session(zenoh_router)
    token = announce(services, keys, "learner", "learner-1")
    changes: list[tuple[set[str], set[str]]] = []
    roster = Roster(
        zenoh_session(zenoh_router), keys, "learner", on_change=lambda joined, left: changes.append((joined, left))
    )
    wait_until(lambda: roster.members() == {"learner-1"})
    roster._members.clear()  # as if the arrival (a history reply) had not landed yet
    token.undeclare()
    wait_until(lambda: (set(), {"learner-1"}) in changes)
    roster.close()


def test_roster_counts_members_and_ignores_other_roles_and_namespaces(zenoh_router, zenoh_session, keys):
    watcher, services = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    roster = Roster(watcher, keys, "encoder")
    tokens = [
        announce(services, keys, "encoder", "enc-1"),
        announce(services, keys, "encoder", "enc-2"),
        announce(services, keys, "sim", "sim-1"),
        announce(services, Keys(keys.namespace + "-other"), "encoder", "enc-x"),
    ]
    assert roster.wait_for(2, timeout_s=VISIBLE_WITHIN_S) == {"enc-1", "enc-2"}
    time.sleep(0.3)  # give a stray token time to arrive, were it (wrongly) routed here
    assert roster.members() == {"enc-1", "enc-2"}
    assert len(tokens) == 4
    roster.close()


def test_roster_started_late_sees_tokens_declared_before_it(zenoh_router, zenoh_session, keys):
    watcher, encoder = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    _token = announce(encoder, keys, "encoder", "enc-early")
    time.sleep(0.2)
    roster = Roster(watcher, keys, "encoder")
    assert roster.wait_for(1, timeout_s=VISIBLE_WITHIN_S) == {"enc-early"}
    roster.close()


def test_wait_for_times_out_naming_the_role_and_the_count(zenoh_router, zenoh_session, keys):
    roster = Roster(zenoh_session(zenoh_router), keys, "encoder")
    started = time.monotonic()
    with pytest.raises(TimeoutError, match=r"no live encoder after 0 s \(need 2, see 0\).*swimm encoder"):
        roster.wait_for(2, timeout_s=0.3)
    assert 0.25 < time.monotonic() - started < 2.0
    roster.close()


def test_a_waiter_wakes_as_soon_as_a_member_joins(zenoh_router, zenoh_session, keys):
    watcher, encoder = zenoh_session(zenoh_router), zenoh_session(zenoh_router)
    roster = Roster(watcher, keys, "encoder")
    seen: list[set[str]] = []
    waiter = threading.Thread(target=lambda: seen.append(roster.wait_for(1, timeout_s=VISIBLE_WITHIN_S)))
    waiter.start()
    time.sleep(0.2)
    _token = announce(encoder, keys, "encoder", "enc-1")
    waiter.join(timeout=VISIBLE_WITHIN_S + 1)
    assert seen == [{"enc-1"}]
    roster.close()


def test_a_killed_process_leaves_the_roster(zenoh_router, zenoh_session, keys, tmp_path):
    """The token of a process that dies without a goodbye (SIGKILL) must go, so its claims and load can move."""
    roster = Roster(zenoh_session(zenoh_router), keys, "encoder")
    script = (
        "import sys, time\n"
        "from services.keys import Keys\n"
        "from services.presence import announce\n"
        "from services.session import open_session\n"
        "from services.settings import ZenohSettings\n"
        f"session = open_session(ZenohSettings(connect=[{zenoh_router!r}], startup_timeout_s=10))\n"
        f"token = announce(session, Keys({keys.namespace!r}), 'encoder', 'enc-doomed')\n"
        "time.sleep(60)\n"
    )
    with open(tmp_path / "doomed.log", "wb") as log:
        process = subprocess.Popen([sys.executable, "-c", script], stdout=log, stderr=subprocess.STDOUT)
    try:
        assert roster.wait_for(1, timeout_s=15.0) == {"enc-doomed"}
        process.kill()
        process.wait(timeout=5)
        left_after = wait_until(lambda: roster.members() == set())
        assert left_after < VISIBLE_WITHIN_S
    finally:
        process.kill()
        process.wait(timeout=5)
        roster.close()
