"""Recorded publications: blocking congestion control and a sequence number on every sample.

Every publisher of the project's recorded channels (`gd2p/**` publications: robot states, object tracks,
worker heartbeats, replays) is a `RecordedPublisher`:

- congestion control BLOCK: a full Zenoh queue makes the publisher wait instead of dropping the sample
  (Zenoh's default, DROP, loses large or fast samples whenever a queue fills: a slow subscriber, the
  recorder writing a 1 MB cloud);
- a sequence attachment on each sample, msgpack `{"publisher": <id>, "seq": <n>}`: `id` names this
  publisher (unique per declaration: `<session zid>.<random>`), `n` counts from 1 without gaps. The
  recorder counts, per key and publisher id, what it received and the gaps in `n` (what it never got);
  `sequence_of` reads the attachment back.

`queue_size` > 0 makes `put` never wait: a sender thread publishes from a queue of that many samples,
and a sample that finds the queue full is dropped *with* its sequence number, so the recorder counts it
missing (`dropped` counts it here). Callers on a control loop (the robot bridge's states) use it: a
loop that stops a robot must never wait for the recorder. Without it (`queue_size=0`) `put` waits while
Zenoh's queue is full (at most Zenoh's `wait_before_close`, 5 s, after which Zenoh closes the link).

The e-stop and the router watchdog's beats are not recorded channels in this sense: they keep their own
settings (shared/bus/lease.py: DROP, since a late beat is worthless; the e-stop is a plain put).
"""
from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
import uuid

import msgpack
import zenoh

log = logging.getLogger("gd2p.bus.recorded")

STREAM_QUEUE = 1000  # the send queue of a stream published from a control loop: 2 s of robot states at 500 Hz

_PUBLISHER = "publisher"
_SEQ = "seq"


def sequence_attachment(publisher_id: str, seq: int) -> bytes:
    """The attachment of sample number `seq` (from 1) of publisher `publisher_id`."""
    packed: bytes = msgpack.packb({_PUBLISHER: publisher_id, _SEQ: int(seq)})
    return packed


def sequence_of(attachment: bytes | None) -> tuple[str, int] | None:
    """(publisher id, sequence number) of a sample's attachment; None when it carries none (or not ours)."""
    if not attachment:
        return None
    try:
        data = msgpack.unpackb(attachment, raw=False)
        publisher, seq = data[_PUBLISHER], data[_SEQ]
    except Exception:  # a foreign attachment: an unsequenced sample
        return None
    if isinstance(publisher, str) and publisher and isinstance(seq, int) and not isinstance(seq, bool) and seq > 0:
        return publisher, seq
    return None


class RecordedPublisher:
    """A Zenoh publisher on `key` with congestion control BLOCK and numbered samples (see the module docstring).

    `priority` and `express` go to Zenoh (express: no batching, for small latency-critical samples).
    `put` returns the sample's sequence number. `close()` sends what is queued (for up to `close_timeout_s`)
    and undeclares.
    """

    def __init__(self, session: zenoh.Session, key: str, *, queue_size: int = 0,
                 priority: zenoh.Priority = zenoh.Priority.DATA, express: bool = False,
                 publisher_id: str | None = None, close_timeout_s: float = 2.0):
        if queue_size < 0:
            raise ValueError(f"queue_size must be >= 0, got {queue_size}")
        self.key = key
        self.publisher_id = publisher_id or f"{session.zid()}.{uuid.uuid4().hex[:8]}"
        self.sent = 0  # samples handed to Zenoh
        self.dropped = 0  # samples that found the queue full (their numbers are gaps the recorder counts)
        self.close_timeout_s = close_timeout_s
        self._publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                    priority=priority, express=express)
        self._seq = 0
        self._lock = threading.Lock()
        self._closed = False
        self._queue: queue.Queue[tuple[bytes, str | None, int] | None] | None = None
        self._sender: threading.Thread | None = None
        if queue_size:
            self._queue = queue.Queue(queue_size)
            self._sender = threading.Thread(target=self._send_all, name=f"publish-{key}", daemon=True)
            self._sender.start()

    @property
    def seq(self) -> int:
        """The last sequence number given out (0 before the first `put`)."""
        return self._seq

    @property
    def matching(self) -> bool:
        """True while a subscriber (e.g. the recorder) matches the key."""
        status = self._publisher.matching_status  # a MatchingStatus at run time (the stub says bool)
        return bool(getattr(status, "matching", status))

    def put(self, payload: bytes, encoding: str | None = None) -> int:
        """Publish one sample with the next sequence number; returns that number."""
        with self._lock:
            if self._closed:
                raise zenoh.ZError(f"publisher on {self.key} is closed")
            self._seq += 1
            seq = self._seq
            if self._queue is None:  # under the lock: numbers go out in order
                self._send(payload, encoding, seq)
                return seq
            try:
                self._queue.put_nowait((payload, encoding, seq))
                return seq
            except queue.Full:
                self.dropped += 1
                dropped = self.dropped
        if dropped == 1 or dropped % 1000 == 0:
            log.warning("%s: %d sample(s) dropped, the send queue was full (the recorder counts them missing)",
                        self.key, dropped)
        return seq

    def put_paced(self, payload: bytes, encoding: str | None, hz: float, seconds: float) -> None:
        """Publish `payload` at `hz` for `seconds` (a load generator for tests and benches): whatever is due each
        tick, so a late tick catches up and the count matches the rate."""
        started = time.monotonic()
        while (elapsed := time.monotonic() - started) < seconds:
            for _ in range(int(elapsed * hz) + 1 - self.seq):
                self.put(payload, encoding=encoding)
            time.sleep(min(0.002, 1.0 / hz))

    def skip(self, count: int = 1) -> None:
        """Use up `count` sequence numbers without publishing (tests: a gap the recorder must count)."""
        with self._lock:
            self._seq += count

    def _send(self, payload: bytes, encoding: str | None, seq: int) -> None:
        self._publisher.put(payload, encoding=encoding, attachment=sequence_attachment(self.publisher_id, seq))
        self.sent += 1

    def _send_all(self) -> None:
        assert self._queue is not None
        while (item := self._queue.get()) is not None:  # None: close
            payload, encoding, seq = item
            try:
                self._send(payload, encoding, seq)
            except zenoh.ZError as exc:  # no router right now: the recorder sees the gap
                log.debug("%s: sample %d not sent: %s", self.key, seq, exc)

    def close(self) -> None:
        """Send what is queued (up to `close_timeout_s`), then undeclare (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._sender is not None and self._queue is not None:
            with contextlib.suppress(queue.Full):
                self._queue.put(None, timeout=self.close_timeout_s)
            self._sender.join(self.close_timeout_s)
            if self._sender.is_alive():  # stuck in a blocked put: the session's close ends it
                log.warning("%s: the sender did not finish within %.1f s", self.key, self.close_timeout_s)
                return
        with contextlib.suppress(zenoh.ZError):
            self._publisher.undeclare()

    def __enter__(self) -> RecordedPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
