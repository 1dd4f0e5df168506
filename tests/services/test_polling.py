"""services/polling.py: an item put by another thread is taken while polling or after it, a timeout still
holds, and the switch interval changes only when polling is asked for."""

from __future__ import annotations

import queue
import sys
import threading
import time

import pytest

from services.polling import POLLING_SWITCH_INTERVAL_S, get_polled, prepare_to_poll


def put_later(inbox: queue.Queue, item: object, delay_s: float) -> threading.Thread:
    thread = threading.Thread(target=lambda: (time.sleep(delay_s), inbox.put(item)))
    thread.start()
    return thread


@pytest.mark.parametrize("delay_s", [0.002, 0.05], ids=["while-polling", "after-polling"])
def test_an_item_put_by_another_thread_is_taken(delay_s: float) -> None:
    inbox: queue.Queue[str] = queue.Queue()
    thread = put_later(inbox, "action", delay_s)
    assert get_polled(inbox, poll_s=0.02, timeout=5.0) == "action"
    thread.join()
    assert inbox.empty()


def test_the_timeout_counts_from_the_call_polling_included() -> None:
    inbox: queue.Queue[str] = queue.Queue()
    start = time.perf_counter()
    with pytest.raises(queue.Empty):
        get_polled(inbox, poll_s=0.05, timeout=0.1)
    assert 0.1 <= time.perf_counter() - start < 0.14


def test_polling_shortens_the_switch_interval_and_blocking_leaves_it() -> None:
    default = sys.getswitchinterval()
    try:
        assert prepare_to_poll(0.0) == 0.0
        assert sys.getswitchinterval() == default
        assert prepare_to_poll(2.0) == pytest.approx(0.002)
        assert sys.getswitchinterval() == pytest.approx(POLLING_SWITCH_INTERVAL_S)
    finally:
        sys.setswitchinterval(default)


def test_a_negative_poll_time_is_refused() -> None:
    with pytest.raises(ValueError, match="poll_ms must be >= 0"):
        prepare_to_poll(-1.0)
