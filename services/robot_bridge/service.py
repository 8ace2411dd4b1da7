"""Bus adapter of the robot_bridge service: executes plans on the simulated robot.

- An `ExecutionCommand` queried on `safety.COMMAND_KEY` (the one key the secure profile lets only
  the planner query) runs on the simulated robot of the plan's arm + hand (`sim_backend.SimExecutor`);
  the reply is the final `ExecutionState`: status "done", "stopped" (e-stop or lost lease), or
  "refused" with a message naming the broken limit, joint and time. The worker's own job key does
  not execute commands (anyone on the bus may query it); it serves health queries and EStop.
- The command's `lease_token` must be a planner's lease, `gd2p/lease/planner/<holder>`, held by a live
  liveliness token (`safety.CommandLease`). It is watched from before the first check until the
  motion ends: a lease lost at any point — during the checks, the world reset or the motion; the
  commander dropped it, or this bridge lost its router — refuses or stops the command, and the final
  state names the loss and how long the halt took. With a `probe` session (what `run` opens), a
  `RouterWatchdog` also notices a router that hangs without closing the link.
- Anything published on `safety.ESTOP_KEY` (or an `EStop` job) stops every robot at once and latches:
  later commands are refused until the bridge restarts (the operator's deliberate action).
- A command with a `world` first resets the simulation to it (object, obstacles, robot at home);
  without one the plan runs in the world the previous command left (multi-step pushes). A command
  whose lease is lost during the reset is refused before anything moves.
- While a plan runs, `ExecutionState`s are published on `STATE_KEY` at the backend's state rate.

Each command runs on a thread of its own, so a second command is answered ("refused: busy") while
one executes. With `--hardware ARM+HAND` the bridge drives real devices instead
(`hardware.HardwareSpec` -> `safety.SafeExecutor`, same lease and e-stop latch); a command for
any other robot is refused, and no simulated world is built.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

from services.robot_bridge.hardware import HardwareSpec, connect_all
from services.robot_bridge.safety import (
    COMMAND_KEY,
    CommandLease,
    EStopLatch,
    SafeExecutor,
    SafetyRefusal,
)
from services.robot_bridge.sim_backend import SimBackend, SimExecutor, StatePublisher
from shared.bus import BusConfig, OpenCancelled, Worker, open_session
from shared.bus.keys import ROBOT_STATE_KEY
from shared.bus.lease import RouterWatchdog
from shared.codec import CodecError, decode, encode
from shared.messages import ErrorReply, EStop, ExecutionCommand, ExecutionState, Message
from shared.objects import ObjectLoadError

SERVICE = "robot_bridge"
STATE_KEY = ROBOT_STATE_KEY

log = logging.getLogger("gd2p.robot_bridge")


class Bridge:
    """One simulated robot per (arm, hand), built on first use, behind lease and e-stop checks.

    `probe`: a second session to the same router; with it a `RouterWatchdog` stops motion when the
    router stops forwarding (hung, or a link that drops packets without closing). The caller keeps
    both sessions.
    """

    def __init__(self, session: zenoh.Session, publish: StatePublisher | None = None, lease_timeout_s: float = 1.0,
                 probe: zenoh.Session | None = None):
        self.session = session
        self.publish = publish
        self.lease_timeout_s = lease_timeout_s
        self.estop_latch = EStopLatch(session, [])
        self.watchdog = (RouterWatchdog(session, probe, f"{SERVICE}-{session.zid()}") if probe is not None
                         else None)
        self._executors: dict[tuple[str, str], SimExecutor] = {}
        self._lock = threading.Lock()
        self.hardware: SafeExecutor | None = None  # set by `attach_hardware`; then no simulated robot is used

    def attach_hardware(self, spec: HardwareSpec) -> None:
        """Connect the real arm and hand (all or none) and route every command to them."""
        devices = spec.devices()
        connect_all(devices)
        self.hardware = SafeExecutor(self.session, spec.arm, spec.hand, devices, publish=self.publish,
                                     estop=self.estop_latch, lease_timeout_s=self.lease_timeout_s,
                                     watchdog=self.watchdog)

    def executor(self, arm: str, hand: str) -> SimExecutor:
        with self._lock:
            if (arm, hand) not in self._executors:
                backend = SimBackend(arm, hand, publish=self.publish)
                backend.connect()
                self.estop_latch.backends.append(backend)
                self._executors[(arm, hand)] = SimExecutor(backend)
            return self._executors[(arm, hand)]

    def execute(self, command: ExecutionCommand) -> ExecutionState:
        """Run `command.plan` if every check passes, watching its lease throughout; the final state (or the refusal)."""
        if self.hardware is not None:
            return self.hardware.execute(command)  # its own lease, e-stop, limit and workspace checks
        executor = self.executor(command.plan.arm, command.plan.hand)
        try:
            with CommandLease(self.session, command.lease_token, watchdog=self.watchdog,
                              confirm_timeout_s=self.lease_timeout_s) as lease:
                self._prepare(executor, command, lease)
                state = executor.execute(command.plan, command.realtime_factor, command.id, lease.stop)
                return self._finish(executor, state, lease, time.monotonic())
        except SafetyRefusal as exc:
            log.warning("refused command %s: %s", command.id, exc)
            return executor.backend.execution_state("refused", command.id, str(exc))

    def _prepare(self, executor: SimExecutor, command: ExecutionCommand, lease: CommandLease) -> None:
        """The checks before the world reset, the reset, and the lease again after it (SafetyRefusal)."""
        if self.estop_latch.triggered.is_set():
            raise SafetyRefusal("estop", f"e-stop is latched ({self.estop_latch.reason()}); restart the bridge "
                                "to clear it")
        lease.require()
        if command.world is not None:
            try:
                executor.backend.reset_world(command.world)
            except ObjectLoadError as exc:
                raise SafetyRefusal("world", str(exc)) from None
            lease.require()  # lost during the reset: nothing has moved yet

    def _finish(self, executor: SimExecutor, state: ExecutionState, lease: CommandLease,
                halted_at: float) -> ExecutionState:
        """Name why a motion stopped (e-stop, lost lease) and make the robot ready after a lease loss."""
        if state.status == "refused":
            log.warning("refused command %s: %s", state.command_id, state.message)
        if state.status != "stopped":
            return state
        why = []
        if self.estop_latch.triggered.is_set():
            why.append(f"e-stop: {self.estop_latch.reason()}")
        else:
            executor.backend.recover()  # a lost lease is not a fault: ready for the next commander
        if lease.lost:
            why.append(lease.stop_note(halted_at))
        return state.model_copy(update={"message": "; ".join([*why, state.message])})

    def estop(self, request: EStop) -> ExecutionState:
        """Stop every robot now and latch; the reply is the state of the first robot (if any)."""
        self.estop_latch.trigger(request)
        with self._lock:
            executors = list(self._executors.values())
        message = f"e-stop: {request.reason}"
        if not executors:
            return ExecutionState(stamp=time.time(), joint_names=[], positions=np.zeros(0), velocities=np.zeros(0),
                                  status="stopped", command_id=request.id, message=f"{message} (no robot was moving)")
        return executors[0].backend.execution_state("stopped", request.id, message)

    def close(self) -> None:
        self.estop_latch.close()
        if self.watchdog is not None:
            self.watchdog.close()
        if self.hardware is not None:
            for device in self.hardware.devices:
                device.backend.disconnect()
            self.hardware = None
        with self._lock:
            for executor in self._executors.values():
                executor.backend.disconnect()
            self._executors.clear()

    def handlers(self) -> dict[type[Message], Callable[[Message], Message]]:
        """Message type -> handler on the worker's job key (commands go to COMMAND_KEY instead)."""
        return {EStop: self.estop}

    def serve_commands(self) -> zenoh.Queryable:
        """Execute ExecutionCommands queried on COMMAND_KEY, each on a thread of its own."""

        def on_query(query: zenoh.Query) -> None:  # zenoh callback: never block here
            threading.Thread(target=self._answer, args=(query,), name="bridge-command", daemon=True).start()

        return self.session.declare_queryable(COMMAND_KEY, on_query)

    def _answer(self, query: zenoh.Query) -> None:
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                command = decode(payload, str(query.encoding) if query.encoding is not None else None, ExecutionCommand)
                if not isinstance(command, ExecutionCommand):
                    raise CodecError(f"{COMMAND_KEY} accepts ExecutionCommand, got {type(command).__name__}")
                reply: Message = self.execute(command)
            except CodecError as exc:
                reply = ErrorReply(code="bad_request", message=str(exc), service=SERVICE)
            except Exception as exc:  # the caller must hear of it, and the bridge keeps serving
                log.exception("command failed")
                reply = ErrorReply(code="internal", message=repr(exc), service=SERVICE)
            payload, encoding = encode(reply)
            query.reply(COMMAND_KEY, payload, encoding=encoding)
        finally:
            query.drop()  # finalise: an unanswered query keeps its caller waiting


def run(cfg: BusConfig, worker_id: str | None = None, stop: threading.Event | None = None,
        hardware: HardwareSpec | None = None) -> None:
    """Serve the robot bridge until SIGTERM/SIGINT or `stop`, publishing states on `STATE_KEY`.

    `hardware` (None = the simulated robot) is connected before the worker registers, so a bridge
    whose devices are absent fails at start with the device's error instead of announcing itself.
    A client bridge opens a second session to its router, the probe of its `RouterWatchdog`.
    """
    try:
        session = open_session(cfg, stop=stop)
    except OpenCancelled:
        log.info("robot_bridge stopped before a router was reachable")
        return
    bridge = probe = None
    try:
        probe = open_session(cfg, stop=stop) if cfg.mode == "client" else None
        publisher = session.declare_publisher(STATE_KEY)

        def publish(state: ExecutionState) -> None:
            payload, encoding = encode(state)
            publisher.put(payload, encoding=encoding)

        bridge = Bridge(session, publish, probe=probe)
        if hardware is not None:
            bridge.attach_hardware(hardware)
        commands = bridge.serve_commands()
        Worker(SERVICE, bridge.handlers(), cfg, worker_id, stop=stop, session=session).run()
        commands.undeclare()
        publisher.undeclare()
    except OpenCancelled:
        log.info("robot_bridge stopped while opening its watchdog session")
    finally:
        if bridge is not None:
            bridge.close()
        if probe is not None:
            probe.close()
        session.close()
