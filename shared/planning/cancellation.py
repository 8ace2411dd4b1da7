"""Cancelling a push request: the requester gave up (Ctrl-C, a crashed client, a lost connection).

A `Cancellation` travels with one request through the pipeline. The service adapter cancels it when
the client's lease is lost; the pipeline checks it between stages and while it waits for the farm,
and the execution step registers a callback that drops the robot command's lease, which stops the
robot (the bridge watches that lease). Nothing here knows about Zenoh.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, wait
from typing import Any

log = logging.getLogger("gd2p.planner.cancellation")

_WAIT_SLICE_S = 0.05  # how often a wait looks at the cancellation


class RequestCancelled(Exception):
    """The request was cancelled; `reason` says by whom or why."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Cancellation:
    """Set once, from any thread; `on_cancel` callbacks run at that moment (or at once if already set)."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._callbacks: list[Callable[[], None]] = []
        self.reason = ""
        self.cancelled_at: float | None = None  # time.monotonic() of the cancellation

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def cancel(self, reason: str) -> None:
        with self._lock:
            if self._event.is_set():
                return
            self.reason = reason
            self.cancelled_at = time.monotonic()
            self._event.set()
            callbacks, self._callbacks = self._callbacks, []
        for callback in callbacks:
            _run(callback)

    def on_cancel(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call `callback` when cancelled; returns a function that unregisters it."""
        with self._lock:
            if not self._event.is_set():
                self._callbacks.append(callback)
                return lambda: self._unregister(callback)
        _run(callback)
        return lambda: None

    def _unregister(self, callback: Callable[[], None]) -> None:
        with self._lock:
            if callback in self._callbacks:
                self._callbacks.remove(callback)

    def check(self) -> None:
        """RequestCancelled if cancelled."""
        if self._event.is_set():
            raise RequestCancelled(self.reason)

    def wait(self, futures: Sequence[Future[Any]], timeout_s: float) -> None:
        """Wait until every future is done or `timeout_s` passed; RequestCancelled as soon as cancelled."""
        deadline = time.monotonic() + timeout_s
        pending = list(futures)
        while pending:
            self.check()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            _, not_done = wait(pending, timeout=min(_WAIT_SLICE_S, remaining))
            pending = list(not_done)
        self.check()


def _run(callback: Callable[[], None]) -> None:
    try:
        callback()
    except Exception:  # one failing callback must not keep the others (the robot's stop) from running
        log.exception("cancellation callback failed")
