"""Messages and a worker entry point for the bus tests (imported by tests and by spawned workers).

A spawned worker runs `python -c "...; bus_test_workers.serve(endpoint, worker_id)"`, so it is a real
separate process with its own Zenoh session, as in production.
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time

from shared.bus import BusConfig, run_worker
from shared.bus.worker import check_deadline
from shared.contracts.errors import ServiceError
from shared.contracts.messages import Message

SERVICE = "bustest"
TESTS_DIR = os.path.dirname(os.path.abspath(__file__))
REPO_DIR = os.path.dirname(TESTS_DIR)


class BusTestJob(Message):
    """Echo `text` after `sleep_s` (and `spin_s`, checking the job's deadline every 10 ms); `fail`
    makes the handler raise (value picks how)."""

    text: str = ""
    sleep_s: float = 0.0
    spin_s: float = 0.0
    fail: str | None = None  # None | "service" | "crash"


class BusTestResult(Message):
    """What the test worker answers: the echoed text and who served it."""

    text: str
    worker_id: str
    pid: int
    concurrent: int  # jobs running in this worker when this one started (itself included)
    max_concurrent: int  # the most this worker has run at once so far


class _Counter:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.now = 0
        self.max = 0


def make_handler(worker_id: str):
    counter = _Counter()

    def handle(job: BusTestJob) -> BusTestResult:
        with counter.lock:
            counter.now += 1
            counter.max = max(counter.max, counter.now)
            concurrent = counter.now
        try:
            if job.fail == "service":
                raise ServiceError("infeasible", f"asked to fail: {job.text}")
            if job.fail == "crash":
                raise ZeroDivisionError("asked to crash")
            time.sleep(job.sleep_s)
            spin(job.spin_s)
            return BusTestResult(text=job.text, worker_id=worker_id, pid=os.getpid(),
                                 concurrent=concurrent, max_concurrent=counter.max)
        finally:
            with counter.lock:
                counter.now -= 1

    return handle


def spin(seconds: float) -> None:
    """Work for `seconds` as a long cooperative job does: in steps, checking the deadline between them."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        check_deadline()
        time.sleep(0.01)


def serve(endpoint: str, worker_id: str, concurrency: int = 1, service: str = SERVICE) -> None:
    """Entry point of a spawned worker process (logs to stderr)."""
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    cfg = BusConfig(mode="client", connect=[endpoint], connect_timeout_ms=-1)
    run_worker(service, {BusTestJob: make_handler(worker_id)}, cfg, worker_id=worker_id, concurrency=concurrency)


def worker_command(endpoint: str, worker_id: str, concurrency: int = 1, service: str = SERVICE) -> list[str]:
    code = (
        f"import sys; sys.path[:0] = [{REPO_DIR!r}, {TESTS_DIR!r}]; import bus_test_workers as w; "
        f"w.serve({endpoint!r}, {worker_id!r}, {concurrency}, {service!r})"
    )
    return [sys.executable, "-c", code]
