"""Worker runtime: serve one service's jobs on the bus.

A worker announces itself with a liveliness token (`gd2p/alive/<service>/<worker_id>`), serves a
queryable of its own (`gd2p/<service>/worker/<worker_id>/job`, so a dispatcher addresses exactly
one worker — Zenoh has no work queue), publishes a `WorkerStatus` heartbeat, and turns every
failure into an `ErrorReply` instead of dying:

- payload that does not decode (CodecError)  -> ErrorReply("bad_request", <what is wrong>)
- a message type the service has no handler for -> ErrorReply("bad_request", "<svc> accepts X, Y ...")
- handler raises ServiceError(code, msg)       -> ErrorReply(code, msg)
- handler raises anything else                 -> ErrorReply("internal", repr(exc)); worker keeps going
- HealthQuery                                  -> WorkerStatus, answered by the runtime itself

Results are stamped with the job's id (so callers correlate them) and cached by job id: a job id
sent again — e.g. re-dispatched after a timeout — gets the cached reply without recomputation, and
a duplicate that arrives while the original still runs is answered when it finishes.

SIGTERM / SIGINT (or the `stop` event): stop accepting (the liveliness token goes first; a query
that still arrives gets ErrorReply "unavailable", which a dispatcher re-dispatches elsewhere), finish
in-flight jobs for up to `drain_timeout_s` (jobs still running then are answered "unavailable" too),
undeclare, close the session. A worker still waiting for its router stops as well.
"""
from __future__ import annotations

import logging
import os
import queue
import signal
import socket
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Mapping

import zenoh

from shared.bus.config import BusConfig, open_session
from shared.bus.errors import OpenCancelled, ServiceError
from shared.bus.keys import alive_key, check_chunk, job_key, status_key
from shared.codec import CodecError, decode, encode
from shared.messages import ErrorReply, HealthQuery, Message, WorkerStatus

log = logging.getLogger("gd2p.bus.worker")

Handler = Callable[[Message], Message]
# Error codes that describe the request, not a passing condition: safe to replay from the cache.
_CACHEABLE_ERRORS = frozenset({"bad_request", "not_implemented", "infeasible"})


class _JobPool:
    """`concurrency` daemon threads running jobs from a queue.

    Daemon threads, unlike ThreadPoolExecutor's, do not hold the process at exit: a worker that
    gives up waiting for a long job on shutdown (see `drain_timeout_s`) can still exit promptly.
    """

    def __init__(self, size: int, name: str):
        self._jobs: queue.Queue = queue.Queue()
        self._idle = threading.Condition()
        self._busy = 0
        self._threads = [threading.Thread(target=self._loop, name=f"{name}-{i}", daemon=True) for i in range(size)]
        for thread in self._threads:
            thread.start()

    def submit(self, fn: Callable, *args) -> None:
        with self._idle:
            self._busy += 1
        self._jobs.put((fn, args))

    def drain(self, timeout: float) -> bool:
        """Wait until every submitted job has finished; False if `timeout` expired first."""
        with self._idle:
            return self._idle.wait_for(lambda: self._busy == 0, timeout)

    def close(self) -> None:
        for _ in self._threads:
            self._jobs.put(None)

    def _loop(self) -> None:
        while (item := self._jobs.get()) is not None:
            fn, args = item
            try:
                fn(*args)
            except Exception:  # fn reports its own errors; this only keeps the thread alive
                log.exception("job thread error")
            finally:
                with self._idle:
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
    ):
        if concurrency < 1:
            raise ValueError(f"concurrency must be >= 1, got {concurrency}")
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
        self._session = session
        self._lock = threading.Lock()
        self._cache: OrderedDict[str, tuple[bytes, str]] = OrderedDict()
        self._cache_size = result_cache_size
        self._running: dict[str, list[zenoh.Query]] = {}  # job id -> queries waiting for its result
        self._stopping = False
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
        pool = _JobPool(self.concurrency, name=f"{self.service}-job")
        try:
            self._serve(session, pool)
        finally:
            pool.close()
            if self._session is None:
                session.close()
            restore()
            log.info("%s worker %s stopped", self.service, self.worker_id)

    # ------------------------------------------------------------------ serving
    def _serve(self, session: zenoh.Session, pool: _JobPool) -> None:
        # Queryable before token: whoever sees the token may query at once (zenoh issue #588).
        queryable = session.declare_queryable(self._reply_key, complete=True)
        publisher = session.declare_publisher(status_key(self.service, self.worker_id))
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
            receiver.join(timeout=5.0)
            # In-flight jobs still reply after the queryable is gone; give them drain_timeout_s.
            if not pool.drain(self.drain_timeout_s):
                self._abandon_running()
            self._publish_status(publisher)
            publisher.undeclare()

    def _abandon_running(self) -> None:
        """Answer the jobs still running with "unavailable", so dispatchers re-dispatch them now."""
        with self._lock:
            running, self._running = self._running, {}
        log.warning("%s worker %s abandons %d job(s) still running after %.1f s",
                    self.service, self.worker_id, len(running), self.drain_timeout_s)
        for job_id, queries in running.items():
            for query in queries:
                self._reply_error(query, "unavailable", f"{self.service} worker {self.worker_id} stopped before "
                                  f"finishing job {job_id}")

    def _publish_status(self, publisher: zenoh.Publisher) -> None:
        payload, encoding = encode(self.status())
        try:
            publisher.put(payload, encoding=encoding)
        except zenoh.ZError as exc:  # no router right now: the heartbeat is best effort
            log.debug("status heartbeat not sent: %s", exc)

    def _receive(self, queryable: zenoh.Queryable, pool: _JobPool) -> None:
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
        payload = query.payload.to_bytes() if query.payload is not None else b""
        encoding = str(query.encoding) if query.encoding is not None else None
        try:
            msg = decode(payload, encoding)
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
        with self._lock:
            cached = self._cache.get(msg.id)
            if cached is None:
                waiting = self._running.get(msg.id)
                if waiting is not None:  # same job already running: answer this query too when it ends
                    waiting.append(query)
                    return
                self._running[msg.id] = [query]
                self._in_flight += 1
        if cached is not None:
            self._reply(query, *cached)
            return
        pool.submit(self._execute, handler, msg)

    def _execute(self, handler: Handler, job: Message) -> None:
        payload, encoding, ok, cacheable = self._compute(handler, job)
        with self._lock:
            queries = self._running.pop(job.id, [])
            self._in_flight -= 1
            self._jobs_done += ok
            self._jobs_failed += not ok
            if cacheable:
                self._cache[job.id] = (payload, encoding)
                if len(self._cache) > self._cache_size:
                    self._cache.popitem(last=False)
        for query in queries:
            self._reply(query, payload, encoding)

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
    **options,
) -> None:
    """Serve `service` with `handlers` until SIGTERM/SIGINT or `stop` is set (see `Worker`).

    `options` go to `Worker` (status_period_s, result_cache_size, drain_timeout_s).
    """
    Worker(service, handlers, cfg, worker_id, concurrency, capabilities, stop, **options).run()
