"""Dispatcher: load-balance jobs over the live workers of one service.

Zenoh has no work queue, so the caller balances explicitly:
- live workers come from a liveliness subscription on `gd2p/alive/<service>/*` (history=True);
- each job goes to the live worker with the fewest jobs in flight, addressed by its own key
  (`gd2p/<service>/worker/<id>/job`), never more than `max_in_flight_per_worker` at once; the rest
  wait in the dispatcher (back-pressure: `submit` blocks while `max_queued` jobs are unfinished);
- each query tells the worker how long the dispatcher waits (`timeout_s`, as the query attachment):
  the worker answers ErrorReply "timeout" just before that instead of working on for nobody; and
  where to see that the dispatcher is still there: it holds a liveliness token `gd2p/caller/<id>`
  until `close()`, and a worker cancels the jobs of a caller whose token is gone;
- every reply is final, ErrorReply included ("timeout" and "bad_request" too: a job too slow or too
  big for one worker is so for all), except "unavailable" (the worker is shutting down), which is
  re-dispatched without counting as an attempt, and "busy" (the worker's queue is full), which is
  re-dispatched as an attempt after a short cool-down of that worker (the last attempt's "busy" is
  the answer);
- a job whose worker's token is DELETEd, whose query ends without a reply, or that gets no reply
  within `timeout_s` (a hung or unreachable worker) is re-dispatched (preferably to another worker) up
  to `max_attempts`; then its future fails with `DispatchError` naming the job, the service and the
  last failure;
- job ids are idempotent: submitting the same job (same id, same content) while it is in flight or
  recently finished returns the same future; submitting a different job under such an id raises
  `BusError` (an id names one job); a reply that arrives after the job was already answered (by an
  earlier attempt) is dropped, so every result reaches the caller exactly once;
- while no worker is live, jobs wait (workers may come up later); bound the wait with
  `call(timeout=...)`, `map(timeout=...)` or `future.result(timeout)`.

Threading: Zenoh callbacks only enqueue events (they never block); one dispatcher thread owns all
scheduling state and resolves the futures. Future done-callbacks therefore run on that thread and
must be quick (do not call the blocking `submit`/`call` from them).
"""
from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, as_completed
from dataclasses import dataclass, field
from typing import Any

import zenoh

from shared.bus.errors import BusError, DispatchError, RemoteError
from shared.bus.keys import alive_pattern, caller_key, check_chunk, job_key, parse_alive_key
from shared.bus.worker import payload_digest, timeout_attachment
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.messages import ErrorReply, Message

log = logging.getLogger("gd2p.bus.dispatcher")

# A worker whose query ended without an answer is skipped for this long: usually it has just died
# and its liveliness DELETE is on the way.
_COOLDOWN_S = 1.0
# Safety margin over Zenoh's own query timeout before the dispatcher gives up on an attempt itself.
_DEADLINE_MARGIN_S = 2.0


@dataclass(eq=False)
class _WorkerState:
    worker_id: str
    key: str
    in_flight: set[_Attempt] = field(default_factory=set)
    draining: bool = False  # answered "unavailable": it is shutting down
    cooldown_until: float = 0.0
    dispatched: int = 0
    answered: int = 0


@dataclass(eq=False)
class _Job:
    msg: Message
    payload: bytes
    encoding: str
    future: Future[Message]
    failures: int = 0
    current: _Attempt | None = None
    failed_on: set[str] = field(default_factory=set)
    last_failure: str = ""


@dataclass(eq=False)
class _Attempt:
    job: _Job
    worker: _WorkerState
    deadline: float
    settled: bool = False  # its slot on the worker has been released


class Dispatcher:
    """Send jobs to the workers of `service`; see the module docstring for the guarantees."""

    def __init__(
        self,
        session: zenoh.Session,
        service: str,
        max_in_flight_per_worker: int = 4,
        timeout_s: float = 60.0,
        max_attempts: int = 3,
        max_queued: int = 10_000,
        remember_completed: int = 1024,
    ):
        if max_in_flight_per_worker < 1 or max_attempts < 1 or max_queued < 1:
            raise ValueError("max_in_flight_per_worker, max_attempts and max_queued must be >= 1")
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        self.service = check_chunk(service, "service")
        self.max_in_flight_per_worker = max_in_flight_per_worker
        self.timeout_s = timeout_s
        self.max_attempts = max_attempts
        self.max_queued = max_queued
        self._session = session
        self._remember = remember_completed
        # Shared with submitters (guarded by _lock).
        self._lock = threading.Lock()
        self._space = threading.Condition(self._lock)  # unfinished count fell / worker set changed
        # job id -> (payload digest, future): unfinished jobs, and the last `remember_completed` finished.
        self._active: dict[str, tuple[str, Future[Message]]] = {}
        self._recent: OrderedDict[str, tuple[str, Future[Message]]] = OrderedDict()
        self._live_ids: list[str] = []
        self._closed = False
        # Owned by the dispatcher thread.
        # (kind, data): the data of each kind is what its handler in `_run` takes.
        self._events: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._workers: dict[str, _WorkerState] = {}
        self._pending: deque[_Job] = deque()
        self._jobs: dict[str, _Job] = {}
        self._next_deadline_check = 0.0
        self.caller = caller_key(f"{session.zid()}.{uuid.uuid4().hex[:12]}")
        self._caller_token = session.liveliness().declare_token(self.caller)
        self._attachment = timeout_attachment(self.timeout_s, self.caller)
        self._thread = threading.Thread(target=self._run, name=f"dispatcher-{service}", daemon=True)
        self._thread.start()
        self._liveliness = session.liveliness().declare_subscriber(
            alive_pattern(service), zenoh.handlers.Callback(self._on_liveliness), history=True
        )

    # ================================================================== public API
    def submit(self, job: Message) -> Future[Message]:
        """Queue `job`; the future resolves to the worker's reply (an `ErrorReply` included).

        Blocks while `max_queued` jobs are unfinished. The future fails with `DispatchError` if no
        worker answered after `max_attempts`, or if the dispatcher is closed first. The same job
        submitted again returns its first future; a different job with a known id raises `BusError`.
        """
        if not isinstance(job, Message):
            raise TypeError(f"jobs must be shared.contracts.messages.Message instances, got {type(job).__name__}")
        payload, encoding = encode(job)
        digest = payload_digest(payload, encoding)
        with self._lock:
            while True:
                if self._closed:
                    raise DispatchError("unavailable", f"the {self.service} dispatcher is closed", job.id)
                existing = self._active.get(job.id) or self._recent.get(job.id)
                if existing is not None:
                    return self._same_job(job, digest, *existing)
                if len(self._active) < self.max_queued:
                    break
                self._space.wait()
            future: Future[Message] = Future()
            future.set_running_or_notify_cancel()  # not cancellable: the job may already be running
            self._active[job.id] = (digest, future)
        self._events.put(("submit", _Job(job, payload, encoding, future)))
        return future

    def _same_job(self, job: Message, digest: str, known_digest: str,
                  future: Future[Message]) -> Future[Message]:
        """The future of an already submitted job; BusError when `job` only shares its id."""
        if digest != known_digest:
            raise BusError(f"job id {job.id} was reused for a different job: this {self.service} dispatcher already "
                           f"has a job {job.id} with other content ({type(job).__name__} ids must name one job)")
        return future

    def call(self, job: Message, timeout: float | None = None) -> Message:
        """Submit and wait; raises `RemoteError` if the worker answered with an `ErrorReply`,
        `DispatchError` if no worker answered, `TimeoutError` after `timeout` seconds."""
        reply = self.submit(job).result(timeout)
        if isinstance(reply, ErrorReply):
            raise RemoteError(reply)
        return reply

    def map(self, jobs: Iterable[Message], timeout: float | None = None) -> Iterator[Message]:
        """Submit every job, then yield the replies in completion order.

        Each reply carries its job's id. Remote errors are yielded as `ErrorReply`; a job no worker
        answered is yielded as `ErrorReply(code="timeout"|"unavailable")` so one lost job does not
        abort a batch.
        """
        futures = {self.submit(job): job for job in jobs}
        for future in as_completed(futures, timeout=timeout):
            try:
                yield future.result()
            except DispatchError as exc:
                job = futures[future]
                yield ErrorReply(id=job.id, code=exc.code, message=exc.message,
                                 request_type=type(job).__name__, service=self.service)

    def wait_for_workers(self, n: int = 1, timeout: float | None = 10.0) -> list[str]:
        """Block until at least `n` workers are live; returns their ids. Raises TimeoutError."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while len(self._live_ids) < n:
                if self._closed:
                    raise DispatchError("unavailable", f"the {self.service} dispatcher is closed")
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise TimeoutError(
                        f"only {len(self._live_ids)} of {n} {self.service} worker(s) live after {timeout} s "
                        f"(is the service running and connected to the same router?)"
                    )
                self._space.wait(remaining)
            return list(self._live_ids)

    def live(self) -> list[str]:
        """Ids of the live workers of the service (from liveliness)."""
        with self._lock:
            return list(self._live_ids)

    def stats(self) -> dict[str, dict[str, int]]:
        """Per live worker: jobs dispatched / answered / in flight (a snapshot; for diagnostics)."""
        done: Future[dict[str, dict[str, int]]] = Future()
        if threading.current_thread() is self._thread:  # called from a future's done-callback
            self._on_stats(done)
        else:
            self._events.put(("stats", done))
        return done.result(timeout=5.0)

    def close(self) -> None:
        """Stop; unfinished futures fail with DispatchError("unavailable"). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._space.notify_all()
        with contextlib.suppress(zenoh.ZError):  # the session was closed first
            self._liveliness.undeclare()
        with contextlib.suppress(zenoh.ZError):  # last: workers cancel this caller's unfinished jobs
            self._caller_token.undeclare()
        self._events.put(("close", None))
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=10.0)

    def __enter__(self) -> Dispatcher:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # ================================================================== zenoh callbacks (never block)
    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            _, worker_id = parse_alive_key(str(sample.key_expr))
        except BusError:
            return
        self._events.put(("alive" if sample.kind == zenoh.SampleKind.PUT else "gone", worker_id))

    def _reply_handler(self, attempt: _Attempt) -> zenoh.handlers.Callback[zenoh.Reply]:
        def on_reply(reply: zenoh.Reply) -> None:
            ok = reply.ok
            if ok is not None:
                self._events.put(("reply", (attempt, ok.payload.to_bytes(), str(ok.encoding), None)))
            else:
                assert reply.err is not None  # a reply is either ok or an error
                self._events.put(("reply", (attempt, b"", "", reply.err.payload.to_string())))

        def on_done() -> None:
            self._events.put(("done", attempt))

        # indirect=False runs these in Zenoh's own thread instead of a hand-off thread: they only
        # enqueue, and it more than doubles throughput with several workers (bench/bus.py).
        callback: zenoh.handlers.Callback[zenoh.Reply] = zenoh.handlers.Callback(on_reply, on_done, indirect=False)
        return callback

    # ================================================================== dispatcher thread
    def _run(self) -> None:
        handlers: dict[str, Callable[[Any], None]] = {
            "submit": self._on_submit, "reply": self._on_reply_event, "done": self._on_query_done,
            "alive": self._on_worker_alive, "gone": self._on_worker_gone, "stats": self._on_stats,
        }
        while True:
            try:
                kind, data = self._events.get(timeout=self._wait_time())
            except queue.Empty:
                kind, data = "tick", None
            while kind != "tick":  # drain everything queued before scheduling once
                if kind == "close":
                    self._fail_all("unavailable", "the dispatcher was closed before the job finished")
                    return
                try:
                    handlers[kind](data)
                except Exception:  # a bug here must not stop the dispatcher thread
                    log.exception("dispatcher event %s failed", kind)
                try:
                    kind, data = self._events.get_nowait()
                except queue.Empty:
                    kind = "tick"
            self._check_deadlines()
            self._assign()

    def _wait_time(self) -> float:
        return 0.25 if self._jobs else 1.0

    # ---------------------------------------------------------------- events
    def _on_submit(self, job: _Job) -> None:
        self._jobs[job.msg.id] = job
        self._pending.append(job)

    def _on_reply_event(self, data: tuple[_Attempt, bytes, str, str | None]) -> None:
        attempt, payload, encoding, error = data
        self._settle(attempt)
        job = attempt.job
        if job.future.done():
            return  # a late duplicate after a re-dispatch: the caller already has this job's result
        if error is not None:
            if job.current is attempt:
                attempt.worker.cooldown_until = time.monotonic() + _COOLDOWN_S
                self._attempt_failed(attempt, f"worker {attempt.worker.worker_id} did not answer ({error})")
            return
        attempt.worker.answered += 1
        try:
            reply: Message = decode(payload, encoding)
        except CodecError as exc:
            reply = ErrorReply(id=job.msg.id, code="internal", service=self.service, request_type=type(job.msg).__name__,
                               message=f"worker {attempt.worker.worker_id} sent an undecodable reply: {exc}")
        if isinstance(reply, ErrorReply) and reply.code == "busy" and job.failures + 1 < self.max_attempts:
            attempt.worker.cooldown_until = time.monotonic() + _COOLDOWN_S
            self._attempt_failed(attempt, f"worker {attempt.worker.worker_id} is busy ({reply.message})")
            return
        if isinstance(reply, ErrorReply) and reply.code == "unavailable":
            # The worker is shutting down; not the job's fault, so it does not count as an attempt.
            attempt.worker.draining = True
            if job.current is attempt:
                job.current = None
                self._pending.appendleft(job)
            return
        self._complete(job, reply)

    def _on_query_done(self, attempt: _Attempt) -> None:
        if attempt.settled:
            return
        self._settle(attempt)
        if not attempt.job.future.done() and attempt.job.current is attempt:
            attempt.worker.cooldown_until = time.monotonic() + _COOLDOWN_S
            self._attempt_failed(attempt, f"worker {attempt.worker.worker_id} ended the query without a reply")

    def _on_worker_alive(self, worker_id: str) -> None:
        if worker_id not in self._workers:
            self._workers[worker_id] = _WorkerState(worker_id, job_key(self.service, worker_id))
            log.info("%s worker %s joined", self.service, worker_id)
            self._publish_live_ids()

    def _on_worker_gone(self, worker_id: str) -> None:
        worker = self._workers.pop(worker_id, None)
        if worker is None:
            return
        log.info("%s worker %s left with %d job(s) in flight", self.service, worker_id, len(worker.in_flight))
        for attempt in list(worker.in_flight):
            self._settle(attempt)
            if not attempt.job.future.done() and attempt.job.current is attempt:
                self._attempt_failed(attempt, f"worker {worker_id} went away (liveliness token deleted)")
        self._publish_live_ids()

    def _on_stats(self, done: Future[dict[str, dict[str, int]]]) -> None:
        done.set_result({
            w.worker_id: {"dispatched": w.dispatched, "answered": w.answered, "in_flight": len(w.in_flight)}
            for w in self._workers.values()
        })

    # ---------------------------------------------------------------- scheduling
    def _assign(self) -> None:
        """Hand pending jobs to the least-loaded eligible workers, within the per-worker limit."""
        now = time.monotonic()
        while self._pending:
            job = self._pending[0]
            if job.future.done():  # answered by an earlier attempt while waiting for a retry
                self._pending.popleft()
                continue
            worker = self._pick_worker(job, now)
            if worker is None:
                return
            self._pending.popleft()
            self._send(job, worker, now)

    def _pick_worker(self, job: _Job, now: float) -> _WorkerState | None:
        best, best_rank = None, None
        for worker in self._workers.values():
            if worker.draining or worker.cooldown_until > now or len(worker.in_flight) >= self.max_in_flight_per_worker:
                continue
            # Fewest in flight first; avoid workers that already failed this job; then spread evenly.
            rank = (len(worker.in_flight), worker.worker_id in job.failed_on, worker.dispatched)
            if best_rank is None or rank < best_rank:
                best, best_rank = worker, rank
        return best

    def _send(self, job: _Job, worker: _WorkerState, now: float) -> None:
        attempt = _Attempt(job, worker, deadline=now + self.timeout_s + _DEADLINE_MARGIN_S)
        job.current = attempt
        worker.in_flight.add(attempt)
        worker.dispatched += 1
        try:
            self._session.get(
                worker.key, self._reply_handler(attempt), payload=job.payload, encoding=job.encoding,
                timeout=self.timeout_s, consolidation=zenoh.ConsolidationMode.NONE,
                attachment=self._attachment,
            )
        except zenoh.ZError as exc:
            self._settle(attempt)
            self._attempt_failed(attempt, f"could not send to worker {worker.worker_id}: {exc}")

    def _settle(self, attempt: _Attempt) -> None:
        if not attempt.settled:
            attempt.settled = True
            attempt.worker.in_flight.discard(attempt)

    def _attempt_failed(self, attempt: _Attempt, reason: str) -> None:
        job = attempt.job
        job.current = None
        job.failures += 1
        job.failed_on.add(attempt.worker.worker_id)
        job.last_failure = reason
        log.warning("%s job %s attempt %d failed: %s", self.service, job.msg.id, job.failures, reason)
        if job.failures >= self.max_attempts:
            self._finish(job, DispatchError(
                "timeout",
                f"{type(job.msg).__name__} {job.msg.id}: no result from a {self.service} worker after "
                f"{job.failures} attempt(s); last failure: {reason}",
                job.msg.id,
            ))
        else:
            self._pending.appendleft(job)  # retries go first: they have waited longest

    def _check_deadlines(self) -> None:
        """Safety net behind Zenoh's own query timeout (which normally fires first)."""
        now = time.monotonic()
        if now < self._next_deadline_check:
            return
        self._next_deadline_check = now + 0.25
        for worker in list(self._workers.values()):
            for attempt in [a for a in worker.in_flight if a.deadline < now]:
                self._settle(attempt)
                if not attempt.job.future.done() and attempt.job.current is attempt:
                    self._attempt_failed(attempt, f"worker {worker.worker_id} timed out after {self.timeout_s} s")

    # ---------------------------------------------------------------- completion
    def _complete(self, job: _Job, reply: Message) -> None:
        self._finish(job, reply)

    def _finish(self, job: _Job, outcome: Message | Exception) -> None:
        job_id = job.msg.id
        self._jobs.pop(job_id, None)
        with self._lock:
            entry = self._active.pop(job_id, None)
            if entry is not None:  # None: the dispatcher is closing and failed it already
                self._recent[job_id] = entry
            while len(self._recent) > self._remember:
                self._recent.popitem(last=False)
            self._space.notify_all()
        if isinstance(outcome, Exception):
            job.future.set_exception(outcome)
        else:
            job.future.set_result(outcome)

    def _fail_all(self, code: str, reason: str) -> None:
        """Fail every unfinished future, including ones submitted but not yet seen by this thread."""
        with self._lock:
            unfinished, self._active = self._active, {}
            self._space.notify_all()
        for job_id, (_, future) in unfinished.items():
            if not future.done():
                job = self._jobs.get(job_id)
                what = f"{type(job.msg).__name__} {job_id}" if job else f"job {job_id}"
                future.set_exception(DispatchError(code, f"{what}: {reason}", job_id))
        self._jobs.clear()

    def _publish_live_ids(self) -> None:
        with self._lock:
            self._live_ids = sorted(self._workers)
            self._space.notify_all()
