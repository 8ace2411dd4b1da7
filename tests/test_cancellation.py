"""The planner's request cancellation: callbacks run once, waits end as soon as it is cancelled."""
from __future__ import annotations

import threading
import time
from concurrent.futures import Future

import pytest

from shared.planning.cancellation import Cancellation, RequestCancelled


def test_callbacks_run_once_when_cancelled_and_at_once_when_registered_late():
    cancel, calls = Cancellation(), []
    unregister = cancel.on_cancel(lambda: calls.append("a"))
    cancel.on_cancel(lambda: calls.append("b"))
    unregister()
    cancel.cancel("client left")
    cancel.cancel("again")
    assert calls == ["b"] and cancel.reason == "client left"
    cancel.on_cancel(lambda: calls.append("late"))
    assert calls == ["b", "late"]
    with pytest.raises(RequestCancelled, match="client left"):
        cancel.check()


def test_a_failing_callback_does_not_keep_the_others_from_running():
    cancel, calls = Cancellation(), []
    cancel.on_cancel(lambda: 1 / 0)
    cancel.on_cancel(lambda: calls.append("stop the robot"))
    cancel.cancel("x")
    assert calls == ["stop the robot"]


def test_waiting_for_the_farm_ends_as_soon_as_the_request_is_cancelled():
    cancel, never = Cancellation(), Future()
    threading.Timer(0.1, cancel.cancel, args=("client left",)).start()
    started = time.monotonic()
    with pytest.raises(RequestCancelled):
        cancel.wait([never], timeout_s=30.0)
    assert time.monotonic() - started < 1.0


def test_waiting_returns_when_every_future_is_done_or_the_time_is_up():
    cancel, done, never = Cancellation(), Future(), Future()
    done.set_result(1)
    cancel.wait([done], timeout_s=5.0)
    started = time.monotonic()
    cancel.wait([never], timeout_s=0.2)
    assert 0.15 < time.monotonic() - started < 2.0
