"""The bus side of the bridge's safety: a command's lease and the e-stop key, on a Zenoh session.

The executor (executor.py) knows a lease and an e-stop only as small interfaces; these are the ones
the bus adapter gives it:

- `CommandLease` (an `executor.Lease`): a command's `lease_token` must be a planner's lease key,
  `gd2p/lease/planner/<identity>/<holder>` (shared/bus/lease.py); any other key is refused, even one with a live
  token behind it (another role's lease, a worker's `gd2p/alive/...` token, a wildcard). A
  `LeaseMonitor` watches it from *before* the first check until the motion ends: the lease must be
  confirmed held before anything moves, and its loss at any moment (the commander dropped it, crashed
  or closed its session; this bridge lost its router; the bridge's `RouterWatchdog` heard nothing
  through the router for its bound) stops motion.
- `EStopSubscriber`: anything published on `ESTOP_KEY` — a valid `EStop`, an empty payload, garbage,
  a wrong encoding, another message type — starts stopping every robot of its `executor.EStopLatch`
  *before* it is decoded or logged, then latches.
- `LeasedExecutor`: an `executor.Executor` whose commands each get their `CommandLease`.
- `ConfirmServer` (`--confirm`): the bus side of a `confirm.ConfirmGate`: it publishes each held plan
  (`PlanHeld`) on `HELD_KEY` and answers `PlanConfirm` queries on `CONFIRM_KEY` (the secure profile lets
  only the operator identity query it) with a `PlanConfirmReply`. The lease and the e-stop above keep
  watching a held command: either ends the hold, and nothing moves.
"""
from __future__ import annotations

import threading
from collections.abc import Callable

import zenoh

from shared.bus.keys import ROBOT_COMMAND_KEY, ROBOT_CONFIRM_KEY, ROBOT_ESTOP_KEY, ROBOT_HELD_KEY
from shared.bus.lease import LeaseError, LeaseMonitor, RouterWatchdog, parse_lease_key
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.messages import (
    ErrorReply,
    EStop,
    ExecutionCommand,
    ExecutionState,
    Message,
    PlanConfirm,
    PlanHeld,
)
from shared.execution.confirm import ConfirmGate
from shared.execution.executor import EStopLatch, Executor
from shared.execution.limits import SafetyRefusal

ESTOP_KEY = ROBOT_ESTOP_KEY
COMMAND_KEY = ROBOT_COMMAND_KEY
HELD_KEY = ROBOT_HELD_KEY
CONFIRM_KEY = ROBOT_CONFIRM_KEY
COMMAND_LEASE_ROLE = "planner"  # the only role whose lease may command motion


# ------------------------------------------------------------------------------------------ lease
def check_command_lease(key: str) -> str:
    """`key` if it is a planner's lease key, `gd2p/lease/planner/<identity>/<holder>`; SafetyRefusal("lease") otherwise.

    Nothing else may keep a command alive, even with a live token behind it: a worker's `gd2p/alive/...`
    token, a client's lease, a wildcard. The key says nothing about who holds its token: Zenoh
    consolidates tokens declared twice on one key, so the bridge cannot count holders. Binding the
    lease to the planner is the secure profile's (only the planner's certificate may declare tokens
    under `gd2p/lease/planner/planner/*`) and the planner's (a fresh key per command).
    """
    try:
        role, _ = parse_lease_key(key)
    except LeaseError as exc:
        raise SafetyRefusal("lease", f"{exc}; a command's lease must be "
                            f"gd2p/lease/{COMMAND_LEASE_ROLE}/<identity>/<holder>") from None
    if role != COMMAND_LEASE_ROLE:
        raise SafetyRefusal("lease", f"lease {key!r} is a {role} lease; only a {COMMAND_LEASE_ROLE} lease "
                            f"(gd2p/lease/{COMMAND_LEASE_ROLE}/<identity>/<holder>) may command motion")
    return key


class CommandLease:
    """One command's lease, watched from before its first check until its motion ends (a context manager).

    Construction refuses a key that is not a planner lease (`check_command_lease`); entering starts a
    `LeaseMonitor` (with the bridge's `RouterWatchdog`, if any), whose loss calls every `on_lost`
    callback. `require()` is the check before motion: the lease must be confirmed held within
    `confirm_timeout_s` and not lost since.
    """

    def __init__(self, session: zenoh.Session, key: str, *, watchdog: RouterWatchdog | None = None,
                 confirm_timeout_s: float = 1.0):
        self.key = check_command_lease(key)
        self.session, self.watchdog = session, watchdog
        self.confirm_timeout_s = confirm_timeout_s
        self._callbacks: list[Callable[[], None]] = []
        self._lock = threading.Lock()
        self._monitor: LeaseMonitor | None = None

    def __enter__(self) -> CommandLease:
        self._monitor = LeaseMonitor(self.session, self.key, on_lost=self._on_lost, watchdog=self.watchdog)
        return self

    def __exit__(self, *exc: object) -> None:
        self._watching().close()

    def _watching(self) -> LeaseMonitor:
        if self._monitor is None:
            raise RuntimeError("CommandLease is watched only inside its `with` block")
        return self._monitor

    def _on_lost(self) -> None:  # the monitor's thread: quick
        with self._lock:
            callbacks, self._callbacks = self._callbacks, []
        for callback in callbacks:
            callback()

    def on_lost(self, callback: Callable[[], None]) -> None:
        with self._lock:
            if not self.lost:
                self._callbacks.append(callback)
                return
        callback()

    @property
    def lost(self) -> bool:
        return self._watching().lost.is_set()

    @property
    def reason(self) -> str:
        return self._watching().reason

    def require(self) -> None:
        """SafetyRefusal("lease") unless the lease is confirmed held and not lost."""
        if not self._watching().wait_confirmed(self.confirm_timeout_s) or self.lost:
            why = self.reason or f"not confirmed held within {self.confirm_timeout_s:g} s"
            raise SafetyRefusal("lease", f"lease {self.key!r} is not alive ({why}); the commander must hold "
                                "its liveliness token there")


class LeasedExecutor:
    """An `Executor` on the bus: each command runs under its own `CommandLease`."""

    def __init__(self, session: zenoh.Session, executor: Executor, *, watchdog: RouterWatchdog | None = None,
                 lease_timeout_s: float = 1.0):
        self.session, self.executor = session, executor
        self.watchdog = watchdog
        self.lease_timeout_s = lease_timeout_s

    @property
    def estop(self) -> EStopLatch:
        latch = self.executor.estop
        if not isinstance(latch, EStopLatch):
            raise TypeError("a bus executor's e-stop is the EStopLatch its subscriber engages")
        return latch

    def execute(self, command: ExecutionCommand) -> ExecutionState:
        """Watch the command's lease from before the first check until the motion ends; the final state."""
        try:
            lease = CommandLease(self.session, command.lease_token, watchdog=self.watchdog,
                                 confirm_timeout_s=self.lease_timeout_s)
        except SafetyRefusal as exc:
            return self.executor.refuse(command, exc)
        with lease:
            return self.executor.execute(command, lease)


# ------------------------------------------------------------------------------------------ e-stop
class EStopSubscriber:
    """Subscribes to ESTOP_KEY: anything published there engages `latch` — stopping first, decoding after."""

    def __init__(self, session: zenoh.Session, latch: EStopLatch):
        self.latch = latch
        self._subscriber = session.declare_subscriber(ESTOP_KEY, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh callback: stop first, describe after
        self.latch.stop_now()
        self.latch.describe(describe_estop(sample))

    def close(self) -> None:
        self._subscriber.undeclare()


def describe_estop(sample: zenoh.Sample) -> EStop:
    """The EStop a sample on the e-stop key stands for; never raises (whatever arrived is a stop)."""
    try:
        msg: Message = decode(sample.payload.to_bytes(), str(sample.encoding), EStop)
    except Exception as exc:  # a malformed stop is still a stop
        return EStop(reason=f"undecodable message on the e-stop key ({type(exc).__name__}: {exc})")
    if isinstance(msg, EStop):
        return msg
    return EStop(reason=f"a {type(msg).__name__} on the e-stop key (not an EStop): treated as a stop")


# ------------------------------------------------------------------------------------------ confirm
class ConfirmServer:
    """Publishes `gate`'s held plans on HELD_KEY and answers PlanConfirm queries on CONFIRM_KEY."""

    def __init__(self, session: zenoh.Session, gate: ConfirmGate):
        self.gate = gate
        self._publisher = session.declare_publisher(HELD_KEY)
        gate.announce = self.publish
        self._queryable = session.declare_queryable(CONFIRM_KEY, self._on_query)

    def publish(self, held: PlanHeld) -> None:
        payload, encoding = encode(held)
        self._publisher.put(payload, encoding=encoding)

    def _on_query(self, query: zenoh.Query) -> None:  # zenoh callback: the gate answers at once
        try:
            reply: Message
            try:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                request = decode(payload, str(query.encoding) if query.encoding is not None else None, PlanConfirm)
                if not isinstance(request, PlanConfirm):
                    raise CodecError(f"{CONFIRM_KEY} accepts PlanConfirm, got {type(request).__name__}")
                reply = self.gate.confirm(request)
            except CodecError as exc:
                reply = ErrorReply(code="bad_request", message=str(exc), service="robot_bridge")
            payload, encoding = encode(reply)
            query.reply(CONFIRM_KEY, payload, encoding=encoding)
        finally:
            query.drop()

    def close(self) -> None:
        self._queryable.undeclare()
        self._publisher.undeclare()
