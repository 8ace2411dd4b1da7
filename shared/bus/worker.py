"""Worker runtime: serve one service's jobs on the bus.

A worker announces itself with a liveliness token (`gd2p/alive/<service>/<worker_id>`), serves a
queryable of its own (`gd2p/<service>/worker/<worker_id>/job`, so a dispatcher addresses exactly
one worker — Zenoh has no work queue), publishes a `WorkerStatus` heartbeat, and turns every
failure into an `ErrorReply` instead of dying:

- payload over its type's MAX_PAYLOAD_BYTES      -> ErrorReply("bad_request", <size and limit>), not even copied
- payload that does not decode (CodecError)     -> ErrorReply("bad_request", <what is wrong>)
- a message type the service has no handler for -> ErrorReply("bad_request", "<svc> accepts X, Y ...")
- a known job id with a different payload       -> ErrorReply("bad_request", "job id ... was reused ...")
- handler raises ServiceError(code, msg)        -> ErrorReply(code, msg)
- handler raises anything else                  -> ErrorReply("internal", repr(exc)); worker keeps going
- the job's deadline passes                     -> ErrorReply("timeout", ...) (see Deadlines)
- `max_queued` jobs already wait for a thread    -> ErrorReply("busy", ...) at once, nothing queued
- the caller that sent the job went away        -> the job is cancelled (see Callers)
- HealthQuery                                   -> WorkerStatus, answered by the runtime itself

Results are stamped with the job's id (so callers correlate them) and cached by job id together
with the SHA-256 of the job's payload: the same job sent again — e.g. re-dispatched after its
worker went quiet — gets the cached reply without recomputation, and a duplicate that arrives while
the original still runs is answered when it finishes. A different job reusing a known id is refused.

Deadlines: every job has a time budget from the moment it is received: the worker's
`job_budget(job)` when the service sizes its jobs (e.g. poses x the measured cost of one), else
`job_deadline_s`, never more than `job_deadline_s`, and shortened to just under the caller's own query
timeout when the caller says it (the dispatcher sends it as the query attachment, `timeout_attachment`). When it passes, the worker
answers the waiting callers with ErrorReply "timeout" (not cached: it says nothing about the job)
and the job stops at its next `check_deadline()` — handlers of long jobs call it between steps
(`current_deadline()` gives the deadline itself). A job still queued when its deadline passes never
starts. A handler that never checks keeps its thread until it returns, and its result is dropped.

Queue: up to `concurrency` jobs run and `max_queued` more wait; past that a job is answered "busy"
at once, so a flood of requests costs neither memory nor hours of queued work. A service whose small
jobs must not wait behind big ones names them (`express(job)`): one more thread runs such a job when
every regular thread is taken (a 1-pose rollout beside two maximal validation jobs).

Callers: a Dispatcher holds a liveliness token `gd2p/caller/<id>` while it is open and names it in the
query attachment (`attached_caller`). The worker watches those tokens; when one is deleted (the caller
closed, crashed or lost its router), its jobs still queued never start and its running jobs stop at
their next `check_deadline()`, which raises ServiceError("cancelled"). A raw query without a caller
key is bounded by its deadline alone.

SIGTERM / SIGINT (or the `stop` event): stop accepting (the liveliness token goes first; a query
that still arrives gets ErrorReply "unavailable", which a dispatcher re-dispatches elsewhere), finish
in-flight jobs for up to `drain_timeout_s` (jobs still running then are answered "unavailable" too),
undeclare, close the session. A worker still waiting for its router stops as well.
"""
from __future__ import annotations

import hashlib
import logging
import math
import os
import queue
import signal
import socket
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import msgpack
import zenoh

from shared.bus.config import BusConfig, open_session
from shared.bus.errors import OpenCancelled
from shared.bus.keys import CALLER_PREFIX, alive_key, check_chunk, job_key, status_key
from shared.bus.recorded import RecordedPublisher
from shared.contracts.codec import CodecError, check_payload_size, decode, encode
from shared.contracts.errors import ServiceError
from shared.contracts.messages import ErrorReply, HealthQuery, Message, WorkerStatus

log = logging.getLogger("gd2p.bus.worker")

# A handler takes the job type it is registered under (a Message subclass), hence Any: Callable is contravariant
# in its argument, and a mapping cannot tie each key's type to its value's argument.
Handler = Callable[[Any], Message]
# Error codes that describe the request, not a passing condition: safe to replay from the cache.
_CACHEABLE_ERRORS = frozenset({"bad_request", "not_implemented", "infeasible"})
# A job's budget when neither the service nor the caller says less: the longest legitimate job of the
# system (a data-engine GenerationJob of a few hundred candidates, cli/dataset.py) takes up to an hour.
DEFAULT_JOB_DEADLINE_S = 3600.0
# Jobs that may wait for a thread beyond the running ones. A Dispatcher sends at most
# `max_in_flight_per_worker` (4 by default) per worker and caller, so 16 leave room for four callers.
DEFAULT_MAX_QUEUED = 16
# The worker answers "timeout" this long (at most a tenth of the budget) before the caller's query
# times out, so the caller gets a final answer instead of re-dispatching the job to another worker.
_REPLY_MARGIN_S = 0.5
_TIMEOUT_KEY = "timeout_s"
_CALLER_KEY = "caller"

_current = threading.local()  # .run: the _Run the calling job thread executes


@dataclass(eq=False)
class _Run:
    """One execution of a job: its payload digest, its deadline and the queries waiting for it."""

    job: Message
    digest: str
    budget_s: float
    deadline: float  # time.monotonic()
    queries: list[zenoh.Query] = field(default_factory=list)
    expired: bool = False  # the deadline passed (or the caller left) and its callers were answered
    caller: str | None = None  # the caller's liveliness key, when it named one
    cancelled: str = ""  # why the job was cancelled (its caller left); empty while it is not
    express: bool = False  # runs on the express thread when the regular ones are taken


def current_deadline() -> float | None:
    """The `time.monotonic()` by which the job run by this thread must end; None outside a job."""
    run = getattr(_current, "run", None)
    return None if run is None else run.deadline


def check_deadline() -> None:
    """Raise ServiceError("timeout") once the job run by this thread is past its deadline.

    Handlers of long jobs call it between steps; outside a worker job it does nothing.
    """
    run = getattr(_current, "run", None)
    if run is None:
        return
    if run.cancelled:
        raise ServiceError("cancelled", run.cancelled)
    if run.expired or time.monotonic() >= run.deadline:
        raise ServiceError("timeout", f"the job ran past its deadline of {run.budget_s:g} s")


def timeout_attachment(timeout_s: float, caller: str | None = None) -> bytes:
    """The query attachment telling a worker how long the caller waits for the answer, and (`caller`) the
    liveliness key it holds while it waits."""
    fields: dict[str, object] = {_TIMEOUT_KEY: float(timeout_s)}
    if caller is not None:
        fields[_CALLER_KEY] = caller
    packed: bytes = msgpack.packb(fields)
    return packed


def _attachment_fields(attachment: bytes | None) -> dict[str, object]:
    try:
        fields = msgpack.unpackb(attachment, raw=False) if attachment else {}
    except Exception:  # not ours: ignore it
        return {}
    return fields if isinstance(fields, dict) else {}


def caller_timeout_s(attachment: bytes | None) -> float | None:
    """The caller's timeout from a query attachment; None when absent or malformed."""
    value = _attachment_fields(attachment).get(_TIMEOUT_KEY)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0:
        return float(value)
    return None


def attached_caller(attachment: bytes | None) -> str | None:
    """The caller's liveliness key from a query attachment (`gd2p/caller/<id>`); None when absent or not one."""
    value = _attachment_fields(attachment).get(_CALLER_KEY)
    if isinstance(value, str) and value.startswith(f"{CALLER_PREFIX}/") and value.count("/") == 2:
        try:
            check_chunk(value.rsplit("/", 1)[1], "caller id")
        except Exception:
            return None
        return value
    return None


def payload_digest(payload: bytes, encoding: str | None) -> str:
    """What identifies a job's content: SHA-256 over its encoding (message type) and payload bytes."""
    digest = hashlib.sha256(f"{encoding}\0".encode())
    digest.update(payload)
    return digest.hexdigest()


class _JobPool:
    """`size` daemon threads running jobs from a queue, plus (`express`) one thread that takes the small
    jobs arriving while every regular thread is taken.

    Daemon threads, unlike ThreadPoolExecutor's, do not hold the process at exit: a worker that
    gives up waiting for a long job on shutdown (see `drain_timeout_s`) can still exit promptly.
    """

    def __init__(self, size: int, name: str, express: bool = False):
        self._size = size
        self._jobs: queue.Queue[tuple[Callable[..., object], tuple[object, ...]] | None] = queue.Queue()
        self._express: queue.Queue[tuple[Callable[..., object], tuple[object, ...]] | None] = queue.Queue()
        self._idle = threading.Condition()
        self._busy = 0  # submitted and not finished
        self._regular_running = 0
        self._threads = [threading.Thread(target=self._loop, args=(self._jobs, True), name=f"{name}-{i}", daemon=True)
                         for i in range(size)]
        if express:
            self._threads.append(threading.Thread(target=self._loop, args=(self._express, False),
                                                  name=f"{name}-express", daemon=True))
        self._has_express = express
        for thread in self._threads:
            thread.start()

    def submit(self, fn: Callable[..., object], *args: object, express: bool = False) -> None:
        with self._idle:
            self._busy += 1
            # Past the regular threads' free capacity (running plus already queued) a small job takes the
            # express lane instead of waiting behind the big ones.
            taken = self._regular_running + self._jobs.qsize() >= self._size
        (self._express if express and self._has_express and taken else self._jobs).put((fn, args))

    def drain(self, timeout: float) -> bool:
        """Wait until every submitted job has finished; False if `timeout` expired first."""
        with self._idle:
            return self._idle.wait_for(lambda: self._busy == 0, timeout)

    def close(self) -> None:
        for _ in range(self._size):
            self._jobs.put(None)
        if self._has_express:
            self._express.put(None)

    def _loop(self, jobs: queue.Queue[tuple[Callable[..., object], tuple[object, ...]] | None], regular: bool) -> None:
        while (item := jobs.get()) is not None:
            fn, args = item
            with self._idle:
                self._regular_running += regular
            try:
                fn(*args)
            except Exception:  # fn reports its own errors; this only keeps the thread alive
                log.exception("job thread error")
            finally:
                with self._idle:
                    self._regular_running -= regular
                    self._busy -= 1
                    self._idle.notify_all()


def default_worker_id() -> str:
    """host-pid-random: unique across hosts, processes and restarts of the same pid."""
    host = "".join(c if c.isalnum() or c in "-_." else "_" for c in socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


class Worker:
    """One worker process (or thread) of `service`. Use `run()` (blocks) or `run_worker(...)`.

    `handlers` maps each accepted message type to a function returning the reply message; it may
    raise `ServiceError(code, message)`. Up to `concurrency` jobs run at once (in threads: handlers
    that release the GIL — torch, numpy, pybullet — overlap; others should scale with processes).
    `job_deadline_s` bounds every job, `job_budget(job)` sizes each job's deadline within it (see Deadlines
    in the module docstring); `max_queued` jobs may wait for a thread, more are answered "busy";
    `express(job)` names the small jobs that get a thread of their own when the others are taken.
    `session` lets a worker share an already open session (it is then not closed by the worker).
    """

    def __init__(
        self,
        service: str,
        handlers: Mapping[type[Message], Handler],
        cfg: BusConfig | None = None,
        worker_id: str | None = None,
        concurrency: int = 1,
        capabilities: list[str] | None = None,
        stop: threading.Event | None = None,
        *,
        session: zenoh.Session | None = None,
        status_period_s: float = 2.0,
        result_cache_size: int = 1024,
        drain_timeout_s: float = 8.0,
        job_deadline_s: float = DEFAULT_JOB_DEADLINE_S,
        job_budget: Callable[[Message], float] | None = None,
        max_queued: int = DEFAULT_MAX_QUEUED,
        express: Callable[[Message], bool] | None = None,
    ):
        if concurrency < 1:
            raise ValueError(f"concurrency must be >= 1, got {concurrency}")
        if not job_deadline_s > 0:
            raise ValueError(f"job_deadline_s must be positive, got {job_deadline_s}")
        if max_queued < 0:
            raise ValueError(f"max_queued must be >= 0, got {max_queued}")
        for msg_type in handlers:
            if not (isinstance(msg_type, type) and issubclass(msg_type, Message)):
                raise TypeError(f"handler keys must be Message subclasses, got {msg_type!r}")
        self.service = check_chunk(service, "service")
        self.worker_id = check_chunk(worker_id or default_worker_id(), "worker id")
        self.handlers = dict(handlers)
        self.cfg = cfg
        self.concurrency = concurrency
        self.capabilities = list(capabilities or [])
        self.stop_event = stop or threading.Event()
        self.status_period_s = status_period_s
        self.drain_timeout_s = drain_timeout_s
        self.job_deadline_s = job_deadline_s
        self.job_budget = job_budget
        self.max_queued = max_queued
        self.express = express
        self._session = session
        self._lock = threading.Lock()
        self._deadline_changed = threading.Condition(self._lock)
        self._cache: OrderedDict[str, tuple[str, bytes, str]] = OrderedDict()  # job id -> (digest, reply, encoding)
        self._cache_size = result_cache_size
        self._running: dict[str, _Run] = {}  # job id -> its execution (waiting queries, deadline)
        self._stopping = False
        self._closed = False  # ends the deadline watcher
        self._started = time.monotonic()
        self._in_flight = 0
        self._jobs_done = 0
        self._jobs_failed = 0
        self._reply_key = job_key(self.service, self.worker_id)
        self._accepts = ", ".join(sorted(t.__name__ for t in self.handlers)) or "only HealthQuery"

    # ------------------------------------------------------------------ public
    def status(self) -> WorkerStatus:
        with self._lock:
            in_flight, done, failed = self._in_flight, self._jobs_done, self._jobs_failed
        state = "stopping" if self._stopping else ("busy" if in_flight >= self.concurrency else "ready")
        return WorkerStatus(
            service=self.service, worker_id=self.worker_id, pid=os.getpid(), host=socket.gethostname(),
            state=state, in_flight=in_flight, jobs_done=done, jobs_failed=failed,
            uptime_s=time.monotonic() - self._started, capabilities=self.capabilities,
        )

    def stop(self) -> None:
        self.stop_event.set()

    def run(self) -> None:
        """Serve until SIGTERM/SIGINT or `stop`; then drain in-flight jobs and close cleanly."""
        restore = self._install_signal_handlers()
        try:
            session = self._session or open_session(self.cfg or BusConfig.from_env(), stop=self.stop_event)
        except OpenCancelled:
            restore()
            log.info("%s worker %s stopped before a router was reachable", self.service, self.worker_id)
            return
        pool = _JobPool(self.concurrency, name=f"{self.service}-job", express=self.express is not None)
        self._closed = False
        watcher = threading.Thread(target=self._watch_deadlines, name=f"{self.service}-deadlines", daemon=True)
        watcher.start()
        try:
            self._serve(session, pool)
        finally:
            self._close_watcher(watcher)
            pool.close()
            if self._session is None:
                session.close()
            restore()
            log.info("%s worker %s stopped", self.service, self.worker_id)

    # ------------------------------------------------------------------ serving
    def _serve(self, session: zenoh.Session, pool: _JobPool) -> None:
        # Queryable before token: whoever sees the token may query at once (https://github.com/eclipse-zenoh/zenoh/issues/588).
        queryable = session.declare_queryable(self._reply_key, complete=True)
        callers = session.liveliness().declare_subscriber(f"{CALLER_PREFIX}/*", self._on_caller)
        # Numbered for the recorder; a queue of its own, so a congested bus never holds up this loop.
        publisher = RecordedPublisher(session, status_key(self.service, self.worker_id), queue_size=8)
        token = session.liveliness().declare_token(alive_key(self.service, self.worker_id))
        receiver = threading.Thread(
            target=self._receive, args=(queryable, pool), name=f"{self.service}-receiver", daemon=True
        )
        receiver.start()
        log.info("%s worker %s serving %s (accepts %s)", self.service, self.worker_id, self._reply_key, self._accepts)
        try:
            self._publish_status(publisher)
            while not self.stop_event.wait(self.status_period_s):
                self._publish_status(publisher)
        finally:
            self._stopping = True
            token.undeclare()  # dispatchers stop choosing this worker
            queryable.undeclare()  # ends the receiver loop
            callers.undeclare()
            receiver.join(timeout=5.0)
            # In-flight jobs still reply after the queryable is gone; give them drain_timeout_s.
            if not pool.drain(self.drain_timeout_s):
                self._abandon_running()
            self._publish_status(publisher)
            publisher.close()

    def _abandon_running(self) -> None:
        """Answer the jobs still running with "unavailable", so dispatchers re-dispatch them now."""
        with self._lock:
            abandoned = [self._expire(job_id, run) for job_id, run in list(self._running.items())]
        log.warning("%s worker %s abandons %d job(s) still running after %.1f s",
                    self.service, self.worker_id, len(abandoned), self.drain_timeout_s)
        for job_id, run, queries in abandoned:
            for query in queries:
                self._reply_error(query, "unavailable", f"{self.service} worker {self.worker_id} stopped before "
                                  f"finishing job {job_id}", job=run.job)

    def _publish_status(self, publisher: RecordedPublisher) -> None:
        payload, encoding = encode(self.status())
        try:
            publisher.put(payload, encoding=encoding)
        except zenoh.ZError as exc:  # no router right now: the heartbeat is best effort
            log.debug("status heartbeat not sent: %s", exc)

    def _receive(self, queryable: zenoh.Queryable[zenoh.handlers.Handler[zenoh.Query]], pool: _JobPool) -> None:
        for query in queryable:
            try:
                self._accept(query, pool)
            except Exception as exc:  # never let one query kill the receiver
                log.exception("failed to accept a query")
                self._reply_error(query, "internal", f"worker failed to accept the query: {exc!r}")

    def _accept(self, query: zenoh.Query, pool: _JobPool) -> None:
        if self._stopping:
            self._reply_error(query, "unavailable", f"{self.service} worker {self.worker_id} is stopping")
            return
        encoding = str(query.encoding) if query.encoding is not None else None
        try:
            msg, payload = self._decode(query, encoding)
        except CodecError as exc:
            self._reply_error(query, "bad_request", str(exc))
            return
        if isinstance(msg, HealthQuery):
            self._reply(query, *encode(self.status().model_copy(update={"id": msg.id})))
            return
        handler = self.handlers.get(type(msg))
        if handler is None:
            self._reply_error(
                query, "bad_request", f"{self.service} accepts {self._accepts}; got {type(msg).__name__}",
                job=msg,
            )
            return
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        run = _Run(msg, payload_digest(payload, encoding), *self._budget(msg, attachment), queries=[query],
                   caller=attached_caller(attachment), express=self.express is not None and self.express(msg))
        if self._admit(msg, run):
            pool.submit(self._execute, handler, run, express=run.express)

    @staticmethod
    def _decode(query: zenoh.Query, encoding: str | None) -> tuple[Message, bytes]:
        """(message, payload bytes); CodecError — for an oversized payload before it is even copied."""
        check_payload_size(len(query.payload) if query.payload is not None else 0, encoding)
        payload = query.payload.to_bytes() if query.payload is not None else b""
        return decode(payload, encoding), payload

    def _budget(self, job: Message, attachment: bytes | None) -> tuple[float, float]:
        """(budget_s, deadline) of a job received now: its size's budget within `job_deadline_s`, or less if
        the caller waits less."""
        budget = self.job_deadline_s
        if self.job_budget is not None:
            budget = min(budget, self.job_budget(job))
        caller = caller_timeout_s(attachment)
        if caller is not None:
            budget = min(budget, caller - min(_REPLY_MARGIN_S, 0.1 * caller))
        return budget, time.monotonic() + budget

    def _admit(self, job: Message, run: _Run) -> bool:
        """Register `run` as `job`'s execution; False when the job is answered or joined instead."""
        [query] = run.queries
        with self._lock:
            cached, running = self._cache.get(job.id), self._running.get(job.id)
            full = self._in_flight >= self._capacity()
            if cached is None and running is None and not full:
                self._running[job.id] = run
                self._in_flight += 1
                self._deadline_changed.notify()  # the deadline watcher may have to wake up sooner
                return True
            if cached is not None:
                same = cached[0] == run.digest
            elif running is not None:
                same = running.digest == run.digest
                if same:  # same job already running: answer this query too when it ends
                    running.queries.append(query)
                    return False
        if cached is None and running is None:  # full: nothing queued, the caller hears it at once
            self._reply_error(query, "busy", f"{self.service} worker {self.worker_id} has {self._capacity()} jobs "
                              "running or queued (its limit); try again later or another worker", job=job)
        elif cached is not None and same:
            self._reply(query, *cached[1:])
        else:
            self._reply_error(query, "bad_request", f"job id {job.id} was reused for a different job: this "
                              f"{self.service} worker already has a job {job.id} with other content", job=job)
        return False

    def _capacity(self) -> int:
        """How many jobs may be running or queued at once."""
        return self.concurrency + (self.express is not None) + self.max_queued

    def _on_caller(self, sample: zenoh.Sample) -> None:  # zenoh callback: quick, never blocks
        """A caller's token went away: cancel its jobs (queued ones never start, running ones stop at their next
        check) and finalise their queries."""
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        key, now = str(sample.key_expr), time.monotonic()
        with self._lock:
            for run in self._running.values():
                if run.caller == key:
                    run.cancelled = f"its caller went away ({key} was deleted)"
                    run.deadline = now  # the deadline watcher takes it out and answers its queries
            self._deadline_changed.notify()

    def _execute(self, handler: Handler, run: _Run) -> None:
        if run.expired:  # its deadline passed while it was queued: the callers have their answer
            payload, encoding, ok, cacheable = b"", "", False, False
        else:
            _current.run = run  # for check_deadline()
            try:
                payload, encoding, ok, cacheable = self._compute(handler, run.job)
            finally:
                _current.run = None
        job_id = run.job.id
        with self._lock:
            if self._running.get(job_id) is run:
                del self._running[job_id]
            queries = [] if run.expired else run.queries  # expired: its callers were answered already
            ok, cacheable = ok and not run.expired, cacheable and not run.expired
            self._in_flight -= 1
            self._jobs_done += ok
            self._jobs_failed += not ok
            if cacheable:
                self._remember(job_id, run.digest, payload, encoding)
        for query in queries:
            self._reply(query, payload, encoding)

    def _remember(self, job_id: str, digest: str, payload: bytes, encoding: str) -> None:
        """Cache a reply (call with the lock held); the oldest entry goes when the cache is full."""
        self._cache[job_id] = (digest, payload, encoding)
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)

    def _compute(self, handler: Handler, job: Message) -> tuple[bytes, str, bool, bool]:
        """Run the handler; returns (payload, encoding, succeeded, cacheable)."""
        try:
            result = handler(job)
            if not isinstance(result, Message):
                raise TypeError(f"handler for {type(job).__name__} returned {type(result).__name__}, not a Message")
            if result.id != job.id:
                result = result.model_copy(update={"id": job.id})
            return (*encode(result), True, True)
        except ServiceError as exc:
            error = self._error(exc.code, exc.message, job)
            return (*encode(error), False, exc.code in _CACHEABLE_ERRORS)
        except Exception as exc:
            log.exception("%s handler failed on %s %s", self.service, type(job).__name__, job.id)
            return (*encode(self._error("internal", repr(exc), job)), False, False)

    # ------------------------------------------------------------------ deadlines
    def _watch_deadlines(self) -> None:
        """Answer "timeout" for every job whose deadline passed, as soon as it passes."""
        while (expired := self._next_expired()) is not None:
            for job_id, run, queries in expired:
                if run.cancelled:
                    log.warning("%s job %s cancelled: %s", self.service, job_id, run.cancelled)
                    code, why = "cancelled", f"job {job_id} was cancelled: {run.cancelled}"
                else:
                    log.warning("%s job %s passed its %.3g s deadline", self.service, job_id, run.budget_s)
                    code, why = "timeout", f"job {job_id} did not finish within its deadline of {run.budget_s:g} s"
                for query in queries:
                    self._reply_error(query, code, f"{self.service} worker {self.worker_id}: {why}", job=run.job)

    def _next_expired(self) -> list[tuple[str, _Run, list[zenoh.Query]]] | None:
        """Wait until jobs pass their deadline and take them out; None once the worker has closed."""
        with self._lock:
            while not self._closed:
                now = time.monotonic()
                expired = [(job_id, run) for job_id, run in self._running.items() if run.deadline <= now]
                if expired:
                    return [self._expire(job_id, run) for job_id, run in expired]
                soonest = min((run.deadline for run in self._running.values()), default=now + 1.0)
                self._deadline_changed.wait(min(max(soonest - now, 0.001), 1.0))
        return None

    def _expire(self, job_id: str, run: _Run) -> tuple[str, _Run, list[zenoh.Query]]:
        """Take a run out of the running jobs (lock held): its thread stops at its next check, its
        result is neither sent nor cached; returns the queries the caller must answer."""
        del self._running[job_id]
        run.expired = True
        queries, run.queries = run.queries, []
        return job_id, run, queries

    def _close_watcher(self, watcher: threading.Thread) -> None:
        with self._lock:
            self._closed = True
            self._deadline_changed.notify_all()
        watcher.join(timeout=5.0)

    # ------------------------------------------------------------------ replies
    def _error(self, code: str, message: str, job: Message | None = None) -> ErrorReply:
        extra = {"id": job.id, "request_type": type(job).__name__} if job is not None else {}
        return ErrorReply(code=code, message=message, service=self.service, **extra)

    def _reply_error(self, query: zenoh.Query, code: str, message: str, job: Message | None = None) -> None:
        self._reply(query, *encode(self._error(code, message, job)))

    def _reply(self, query: zenoh.Query, payload: bytes, encoding: str) -> None:
        """Reply and finalise the query (an unfinalised query keeps its caller waiting)."""
        try:
            query.reply(self._reply_key, payload, encoding=encoding)
        except zenoh.ZError as exc:  # the caller may be gone; nothing else to do
            log.debug("reply not delivered: %s", exc)
        finally:
            query.drop()

    # ------------------------------------------------------------------ signals
    def _install_signal_handlers(self) -> Callable[[], None]:
        """SIGTERM/SIGINT set the stop event (only possible from the main thread)."""
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
        for sig in previous:
            signal.signal(sig, lambda signum, frame: self.stop_event.set())

        def restore() -> None:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

        return restore


def run_worker(
    service: str,
    handlers: Mapping[type[Message], Handler],
    cfg: BusConfig | None = None,
    worker_id: str | None = None,
    concurrency: int = 1,
    capabilities: list[str] | None = None,
    stop: threading.Event | None = None,
    **options: Any,  # passed on to Worker
) -> None:
    """Serve `service` with `handlers` until SIGTERM/SIGINT or `stop` is set (see `Worker`).

    `options` go to `Worker` (status_period_s, result_cache_size, drain_timeout_s, job_deadline_s).
    """
    Worker(service, handlers, cfg, worker_id, concurrency, capabilities, stop, **options).run()
