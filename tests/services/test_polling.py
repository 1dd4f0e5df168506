"""services/polling.py: an Inbox hands over items put by other threads and Zenoh samples (from a real router)
in order, blocking, while polling or napping after it; its timeout holds; and building one leaves the switch
interval alone (the entry point sets it: tests/services/test_process.py)."""

from __future__ import annotations

import queue
import sys
import threading
import time

import pytest
import zenoh

from services.polling import NAP_MAX_S, POLLING_SWITCH_INTERVAL_S, Inbox, poll_seconds
from services.process import ProcessSettings, configure_process

#: Blocking, and polling for 20 ms before napping.
INBOX_POLL_S = pytest.mark.parametrize("poll_s", [0.0, 0.02], ids=["blocking", "polling"])


def put_later(inbox: Inbox, item: object, delay_s: float) -> threading.Thread:
    thread = threading.Thread(target=lambda: (time.sleep(delay_s), inbox.put(item)))
    thread.start()
    return thread


@pytest.mark.parametrize(
    "poll_s, delay_s", [(0.0, 0.002), (0.02, 0.002), (0.02, 0.05)], ids=["blocking", "while-polling", "after-polling"]
)
def test_an_item_put_by_another_thread_is_taken(poll_s: float, delay_s: float) -> None:
    inbox: Inbox[str] = Inbox(poll_s)
    thread = put_later(inbox, "lapse", delay_s)
    assert inbox.get(timeout=5.0) == "lapse"
    thread.join()
    with pytest.raises(queue.Empty):
        inbox.get(timeout=0.0)


def test_a_polling_inbox_leaves_the_switch_interval_to_the_entry_point() -> None:
    default = sys.getswitchinterval()
    try:
        assert poll_seconds(0.0) == 0.0
        assert poll_seconds(2.0) == pytest.approx(0.002)
        Inbox(poll_seconds(2.0))
        assert sys.getswitchinterval() == default  # no side effect of library code
        configure_process(ProcessSettings(poll_ms=0.0))
        assert sys.getswitchinterval() == default  # blocking leaves it
        configure_process(ProcessSettings(poll_ms=2.0))
        assert sys.getswitchinterval() == pytest.approx(POLLING_SWITCH_INTERVAL_S)
    finally:
        sys.setswitchinterval(default)


def test_a_negative_poll_time_is_refused() -> None:
    with pytest.raises(ValueError, match="poll_ms must be >= 0"):
        poll_seconds(-1.0)
    with pytest.raises(ValueError, match="poll_ms must be >= 0"):
        configure_process(ProcessSettings(poll_ms=-1.0))


def open_inbox(session: zenoh.Session, poll_s: float, key: str) -> tuple[Inbox[str], zenoh.Subscriber]:
    inbox: Inbox[str] = Inbox(poll_s)
    return inbox, inbox.subscribe(session, key, lambda sample: "sample " + sample.payload.to_string())


@INBOX_POLL_S
def test_an_inbox_hands_over_samples_in_order_and_items_from_other_threads(
    zenoh_router, zenoh_session, namespace, poll_s
) -> None:
    session = zenoh_session(zenoh_router)
    key = f"{namespace}/inbox"
    inbox, subscriber = open_inbox(session, poll_s, key)
    for n in range(5):
        session.put(key, str(n))
    assert [inbox.get(timeout=5.0) for _ in range(5)] == [f"sample {n}" for n in range(5)]
    thread = put_later(inbox, "from a timer", 0.05)  # after the polling time: taken from a nap
    assert inbox.get(timeout=5.0) == "from a timer"
    thread.join()
    subscriber.undeclare()


def test_a_polling_inbox_gives_waiting_samples_before_the_queues_items(zenoh_router, zenoh_session, namespace) -> None:
    """The sim's stop puts a sentinel behind the actions that came before it; none may be left behind it."""
    session = zenoh_session(zenoh_router)
    key = f"{namespace}/inbox"
    inbox, subscriber = open_inbox(session, 0.02, key)
    session.put(key, "action")
    time.sleep(0.2)  # the sample waits in its channel
    inbox.put("stop")
    assert [inbox.get(timeout=5.0), inbox.get(timeout=5.0)] == ["sample action", "stop"]
    subscriber.undeclare()


@INBOX_POLL_S
def test_an_empty_inbox_times_out_on_time_and_zero_means_only_what_is_there(
    zenoh_router, zenoh_session, namespace, poll_s
) -> None:
    inbox, subscriber = open_inbox(zenoh_session(zenoh_router), poll_s, f"{namespace}/inbox")
    start = time.perf_counter()
    with pytest.raises(queue.Empty):
        inbox.get(timeout=0.1)
    assert 0.1 <= time.perf_counter() - start < 0.1 + 2 * NAP_MAX_S + 0.03
    inbox.put("now")
    assert inbox.get(timeout=0.0) == "now"
    with pytest.raises(queue.Empty):
        inbox.get(timeout=0.0)
    subscriber.undeclare()
