"""Bus adapter of the planner service: a PushRequest in, a PushResponse out.

The algorithm is `pipeline.PushPipeline`; this module gives it its services over Zenoh:
- sampling: `SampleRequest` through a Dispatcher to the sampler workers;
- arm rollouts: `ValidationJob(with_arm=True)` through a Dispatcher to the validator farm, all plans
  of a push at once (they run in parallel on as many validator processes as there are);
- execution: an `ExecutionCommand` queried on the robot bridge's command key under a lease of its
  own (a liveliness token `gd2p/lease/planner/planner/<worker id>.<command id>`, declared for that command
  only), while the robot's `ExecutionState` stream is collected for the recording;
- cancellation: every request must name its client's lease (`PushRequest.client_lease`; without one
  it is refused, ErrorReply "bad_request"), watched (`shared.bus.lease.LeaseMonitor`) from when the
  request starts; when the lease is lost (Ctrl-C, a crashed client, a lost router) the request is
  cancelled: sampling and planning stop at their next check, and a running command's lease is
  dropped, which stops the robot (the bridge notices within its lease bound). The reply is ErrorReply
  "cancelled". A request whose client left while it was queued is cancelled before it starts (its
  Dispatcher's caller token is gone, or its lease is not found when the request starts).
- queue: one request runs (one robot) and at most MAX_QUEUED wait; more are answered "busy" at once.

Each request is recorded (`recording.py`): an MCAP with Foxglove channels and the bus messages
(written before the answer), and a PNG storyboard beside it (rendered just after), in `record_dir` (`--record-dir`, env GD2P_PUSH_RECORD_DIR, default
`recordings/pushes`); the response names the MCAP.
"""
from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import zenoh

from services.planner.recording import record_push
from shared.bus import BusConfig, Dispatcher, OpenCancelled, RemoteError, Worker, open_session
from shared.bus.errors import DispatchError
from shared.bus.keys import PLANNER_DECISION_KEY, ROBOT_COMMAND_KEY, ROBOT_STATE_KEY
from shared.bus.lease import LeaseError, LeaseMonitor, lease_key, parse_lease_key
from shared.bus.recorded import RecordedPublisher
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.errors import ServiceError
from shared.contracts.messages import (
    ErrorReply,
    ExecutionCommand,
    ExecutionState,
    Plan,
    PushDecision,
    PushRequest,
    PushResponse,
    SampleRequest,
    SampleResponse,
    SimWorld,
    ValidationJob,
    new_id,
)
from shared.planning.cancellation import Cancellation, RequestCancelled
from shared.planning.decision_tap import DecisionTap
from shared.planning.monitor import PushMonitor
from shared.planning.outcome import Execution, PushError
from shared.planning.pipeline import PushPipeline, PushServices

SERVICE = "planner"
RECORD_DIR_ENV = "GD2P_PUSH_RECORD_DIR"
DEFAULT_RECORD_DIR = "recordings/pushes"
SAMPLE_TIMEOUT_S = 60.0
ROLLOUT_TIMEOUT_S = 120.0
EXECUTION_TIMEOUT_S = 300.0
MAX_QUEUED = 4  # push requests waiting behind the running one; more are answered "busy" at once
NOT_CONFIRMED = "not_confirmed:"  # how the bridge's refusal of a plan nobody confirmed starts (`--confirm`)
REALTIME_FACTOR = 1000.0  # the simulated robot runs as fast as it can (physics keeps the plan's timing)

log = logging.getLogger("gd2p.planner")


class BusServices:
    """The pipeline's services over an open Zenoh session."""

    def __init__(self, session: zenoh.Session, worker_id: str):
        self.session = session
        self.sampler = Dispatcher(session, "sampler", timeout_s=SAMPLE_TIMEOUT_S)
        self.validator = Dispatcher(session, "validator", timeout_s=ROLLOUT_TIMEOUT_S, max_in_flight_per_worker=1)
        self.worker_id = worker_id
        self._states: dict[str, list[ExecutionState]] = {}
        self._monitors: dict[str, tuple[PushMonitor, Cancellation]] = {}  # command id -> closed-loop monitor, lease
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(ROBOT_STATE_KEY, self._on_state)
        self._decisions = RecordedPublisher(session, PLANNER_DECISION_KEY, queue_size=16)

    def publish_decision(self, decision: PushDecision) -> None:
        """What the planner chose for a push, for the live view (gd2p/planner/decision); never waits."""
        payload, encoding = encode(decision)
        self._decisions.put(payload, encoding)

    def close(self) -> None:
        self._subscriber.undeclare()
        self._decisions.close()
        self.sampler.close()
        self.validator.close()

    def services(self) -> PushServices:
        return PushServices(sample=self.sample, validate=self.validate, execute=self.execute)

    def sample(self, request: SampleRequest) -> SampleResponse:
        try:
            return self.sampler.call(request, timeout=SAMPLE_TIMEOUT_S * 2)
        except RemoteError as exc:
            raise PushError(exc.code, f"sampler: {exc.message}") from exc
        except (DispatchError, TimeoutError) as exc:
            raise PushError("unavailable", f"no sampler answered: {exc}") from exc

    def validate(self, job: ValidationJob) -> Future:
        """Send `job` to the validator farm; the future's result is the ValidationResult (a RemoteError
        when the validator refused it, the Dispatcher's error when none answered)."""
        outcome: Future = Future()

        def settle(reply: Future) -> None:
            try:
                result = reply.result()
            except Exception as exc:  # DispatchError, TimeoutError: the caller reports them
                outcome.set_exception(exc)
                return
            if isinstance(result, ErrorReply):
                outcome.set_exception(RemoteError(result))
            else:
                outcome.set_result(result)

        self.validator.submit(job).add_done_callback(settle)
        return outcome

    def execute(self, plan: Plan, world: SimWorld | None, cancel: Cancellation,
                monitor: PushMonitor | None = None) -> Execution:
        """Query the bridge with `plan` under a lease of this command alone; cancelling drops the lease, and
        so does `monitor` (closed loop) when the states' tracked object poses give it a reason to stop."""
        command_id = new_id()
        command = ExecutionCommand(id=command_id, plan=plan, lease_token=lease_key(SERVICE, f"{self.worker_id}.{command_id}"),
                                   realtime_factor=REALTIME_FACTOR, world=world)
        stop = Cancellation()  # this command's lease: dropped by the request's cancellation or by the monitor
        unlink = cancel.on_cancel(lambda: stop.cancel("the request was cancelled"))
        with self._lock:
            self._states[command.id] = []
            if monitor is not None:
                self._monitors[command.id] = (monitor, stop)
        payload, encoding = encode(command)
        try:
            # Declared on this session before the query: the router has the token when the command arrives.
            with _held_lease(self.session, command.lease_token, stop):
                replies = list(self.session.get(ROBOT_COMMAND_KEY, payload=payload, encoding=encoding,
                                                timeout=EXECUTION_TIMEOUT_S))
        finally:
            unlink()
            with self._lock:
                states = self._states.pop(command.id)
                self._monitors.pop(command.id, None)
        answers = [r.ok for r in replies if r.ok is not None]
        if not answers:
            raise PushError("unavailable", "no robot bridge answered the execution command")
        try:
            reply = decode(answers[0].payload.to_bytes(), str(answers[0].encoding))
        except CodecError as exc:
            raise PushError("internal", f"robot bridge reply: {exc}") from exc
        if isinstance(reply, ErrorReply):
            raise PushError(reply.code if reply.code in ErrorReply.CODES else "internal", f"robot bridge: {reply.message}")
        if isinstance(reply, ExecutionState) and reply.status == "refused" and reply.message.startswith(NOT_CONFIRMED):
            # Held for an operator (`--confirm`) who did not confirm: nothing moved, and nobody asked for it again.
            raise PushError("not_confirmed", f"robot bridge: the plan was not confirmed: {reply.message}")
        return Execution(final=reply, states=states)

    @contextlib.contextmanager
    def watch_client(self, request: PushRequest, cancel: Cancellation) -> Iterator[None]:
        """Cancel the request when its client's lease is lost. Every push request moves the robot, so a
        request without a lease is refused: nobody could stop a motion whose client has gone."""
        if request.client_lease is None:
            raise ServiceError("bad_request", "client_lease is required: a push request moves the robot, so its "
                               f"client must hold a lease ({lease_key('client', '<id>')}, a liveliness token held "
                               "while it waits) and name it in PushRequest.client_lease; the request is cancelled "
                               "when the token goes (client/push_client.py does this)")
        try:
            role, _ = parse_lease_key(request.client_lease)
        except LeaseError as exc:
            raise ServiceError("bad_request", str(exc)) from exc
        if role != "client":
            raise ServiceError("bad_request", f"client_lease {request.client_lease!r} is not a client lease "
                               f"({lease_key('client', '<id>')})")
        with LeaseMonitor(self.session, request.client_lease,
                          on_lost=lambda: cancel.cancel("the client gave up (its lease was lost)")) as monitor:
            # Confirmed before any work: a loss noticed only later (on a loaded machine, after the plan was
            # sent) would let a robot start for a client that was already gone.
            if not monitor.wait_confirmed():
                cancel.cancel(f"the client's lease is not held: {monitor.reason or 'not confirmed in time'}")
            yield

    def _on_state(self, sample: zenoh.Sample) -> None:  # zenoh callback: quick, never blocks
        try:
            state = decode(sample.payload.to_bytes(), str(sample.encoding), ExecutionState)
        except CodecError:
            return
        with self._lock:
            if state.command_id in self._states:
                self._states[state.command_id].append(state)
            watching = self._monitors.get(state.command_id) if state.command_id is not None else None
        if watching is not None:
            monitor, stop = watching
            reason = monitor.observe_state(state)
            if reason is not None:
                stop.cancel(f"closed loop: {reason}")


def _no_watch(_request: PushRequest, _cancel: Cancellation) -> contextlib.AbstractContextManager:
    return contextlib.nullcontext()


@contextlib.contextmanager
def _held_lease(session: zenoh.Session, key: str, cancel: Cancellation) -> Iterator[None]:
    """Hold a liveliness token on `key` until the block ends or `cancel` fires, whichever is first."""
    token = session.liveliness().declare_token(key)
    released = threading.Lock()

    def release() -> None:
        if released.acquire(blocking=False):
            token.undeclare()

    unregister = cancel.on_cancel(release)
    try:
        yield
    finally:
        unregister()
        release()


ClientWatch = Callable[[PushRequest, Cancellation], contextlib.AbstractContextManager]


class PlannerService:
    """Serves PushRequests: runs the pipeline, records the request, answers.

    `watch_client(request, cancel)` is a context manager that cancels `cancel` when the request's
    client gives up (the bus adapter's `BusServices.watch_client`; default: never).
    """

    def __init__(self, services: PushServices, record_dir: str | os.PathLike | None = None,
                 watch_client: ClientWatch = _no_watch, on_decision: Callable[[PushDecision], None] | None = None):
        # Each push's decision (candidates, rollouts, the chosen plan) goes to `on_decision` before the robot
        # moves (the live view) and into the recording.
        self.tap = DecisionTap(services, on_decision)
        self.pipeline = PushPipeline(self.tap.services())
        self.watch_client = watch_client
        self.record_dir = Path(record_dir or os.environ.get(RECORD_DIR_ENV, DEFAULT_RECORD_DIR)).resolve()
        self._lock = threading.Lock()  # one robot: one push request at a time
        # Storyboards are rendered after the answer, one at a time (they take about as long as a push).
        self._storyboards = ThreadPoolExecutor(max_workers=1, thread_name_prefix="planner-storyboard")

    def push(self, request: PushRequest) -> PushResponse:
        """Plan, rank and execute a push of `request.object`; record it. ErrorReply "cancelled" when
        the client gave up first."""
        cancel = Cancellation()
        try:
            with self.watch_client(request, cancel), self._lock:
                self.tap.begin(request.id)
                outcome = self.pipeline.run(request, cancel)
                decisions = list(self.tap.decisions)
        except PushError as exc:
            raise ServiceError(exc.code, exc.message) from exc
        except RequestCancelled as exc:
            log.warning("push %s cancelled: %s", request.id, exc.reason)
            raise ServiceError("cancelled", exc.reason) from exc
        response = outcome.response
        started = time.perf_counter()
        try:
            with self.pipeline.scene(request.arm, request.hand) as scene:
                path = record_push(self.record_dir, request, outcome, scene, decisions=decisions,
                                   defer=lambda render: self._storyboards.submit(_render_logged, render),
                                   settings=self.pipeline.settings)
        except OSError as exc:
            log.warning("could not record push %s: %s", request.id, exc)
            return response
        timings = response.timings_s | {"recording": time.perf_counter() - started}
        return response.model_copy(update={"recording_path": str(path), "timings_s": timings})

    def handlers(self):
        return {PushRequest: self.push}

    def close(self) -> None:
        """Finish the storyboards still being rendered, release the pipeline's scenes."""
        self._storyboards.shutdown(wait=True)
        self.pipeline.close()


def _render_logged(render) -> None:
    try:
        log.info("storyboard written: %s", render())
    except Exception:  # on a background thread: nobody else would hear of it
        log.exception("storyboard rendering failed")


def run(cfg: BusConfig, worker_id: str | None = None, stop: threading.Event | None = None,
        record_dir: str | None = None) -> None:
    """Serve the planner until SIGTERM/SIGINT or `stop`."""
    import torch

    # Batched IK (the request's "ik" stage) runs while the validators wait for work: every core helps.
    torch.set_num_threads(os.cpu_count() or 1)
    from shared.bus import default_worker_id

    worker_id = worker_id or default_worker_id()
    try:
        session = open_session(cfg, stop=stop)
    except OpenCancelled:
        log.info("planner stopped before a router was reachable")
        return
    bus = service = None
    try:
        bus = BusServices(session, worker_id)
        service = PlannerService(bus.services(), record_dir, watch_client=bus.watch_client,
                                 on_decision=bus.publish_decision)
        Worker(SERVICE, service.handlers(), cfg, worker_id, stop=stop, session=session, max_queued=MAX_QUEUED).run()
    finally:
        if service is not None:
            service.close()
        if bus is not None:
            bus.close()
        session.close()
