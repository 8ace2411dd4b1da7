"""Recorder service: every sample under `gd2p/**` into rotating MCAP files.

A FIFO channel handler receives samples (never a blocking callback); one thread writes them. The
recorder is a worker of the runtime in `shared.bus` like every service: liveliness token
`gd2p/alive/recorder/<worker_id>`, health queries, status heartbeat (which it records too).

Shutdown (SIGTERM / SIGINT) loses nothing that reached the recorder: the liveliness token goes
first, the subscriber stays until the bus has been quiet for `drain_quiet_s` (samples still in
flight arrive), then it is undeclared, the channel is drained to the end, and the file is closed
with its MCAP footer.

Each sample's sequence attachment (shared/bus/recorded.py) goes to the recorder, which counts per key
and publisher what it received and what it never got, into each file's metadata (recorder.py).
"""
from __future__ import annotations

import logging
import threading
import time

import zenoh

from shared.bus import ALL_KEYS, Worker, sequence_of
from visualisation.recorder import RotatingRecorder

log = logging.getLogger("gd2p.recorder")

SERVICE = "recorder"


class RecorderService:
    """Subscribe to `key_expr` and hand every sample to a `RotatingRecorder`."""

    def __init__(
        self,
        recorder: RotatingRecorder,
        key_expr: str = ALL_KEYS,
        *,
        channel_capacity: int = 65536,
        # Quiet is judged by when the writer last took a sample, so on a loaded machine samples still in the
        # router can trail it: 0.3 s lost the last 77 of 400 under a full test suite on 2 cores (CI run of 4856d87).
        drain_quiet_s: float = 1.0,
        drain_max_s: float = 5.0,
    ):
        self.recorder = recorder
        self.key_expr = key_expr
        self.channel_capacity = channel_capacity
        self.drain_quiet_s = drain_quiet_s
        self.drain_max_s = drain_max_s
        self._last_receive = time.monotonic()
        self.write_errors = 0

    def run(self, session: zenoh.Session, worker_id: str | None = None, stop: threading.Event | None = None) -> None:
        """Record until SIGTERM/SIGINT or `stop`; then drain, flush and close the file."""
        # A full FIFO blocks the session's receive path (back-pressure) instead of dropping samples.
        subscriber = session.declare_subscriber(self.key_expr, zenoh.handlers.FifoChannel(self.channel_capacity))
        writer = threading.Thread(target=self._write_all, args=(subscriber.handler,), name="recorder-writer", daemon=True)
        writer.start()
        worker = Worker(SERVICE, {}, worker_id=worker_id, capabilities=["mcap"], stop=stop, session=session)
        try:
            worker.run()  # liveliness + health + heartbeat; returns on SIGTERM/SIGINT/stop
        finally:
            self._wait_until_quiet()
            subscriber.undeclare()  # the channel closes; the writer drains what is buffered, then ends
            writer.join()
            files = self.recorder.close()
            log.info("recorder %s stopped: %d messages in %d file(s)", worker.worker_id, self.recorder.message_count, len(files))

    def _write_all(self, channel: zenoh.Handler) -> None:
        for sample in channel:
            self._last_receive = time.monotonic()
            if sample.kind != zenoh.SampleKind.PUT:
                continue  # a DELETE carries no message to record
            try:
                self.recorder.record(
                    str(sample.key_expr),
                    sample.payload.to_bytes(),
                    str(sample.encoding),
                    time.time_ns(),
                    _timestamp_ns(sample.timestamp),
                    sequence_of(sample.attachment.to_bytes() if sample.attachment is not None else None),
                )
            except Exception:  # one bad write (e.g. disk full) must not stop the recording thread
                self.write_errors += 1
                log.exception("failed to record a sample on %s", sample.key_expr)

    def _wait_until_quiet(self) -> None:
        deadline = time.monotonic() + self.drain_max_s
        while time.monotonic() < deadline and time.monotonic() - self._last_receive < self.drain_quiet_s:
            time.sleep(self.drain_quiet_s / 4)


def _timestamp_ns(stamp: zenoh.Timestamp | None) -> int | None:
    """A Zenoh sample timestamp (present when the publisher's session stamps samples) in Unix ns."""
    if stamp is None:
        return None
    return int(stamp.get_time().timestamp() * 1e9)
