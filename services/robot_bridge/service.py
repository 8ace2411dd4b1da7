"""Bus adapter of the robot_bridge service: executes plans on the simulated robot (issue 6).

- An `ExecutionCommand` queried on `safety.COMMAND_KEY` (the one key the secure profile lets only
  the planner query) runs on the simulated robot of the plan's arm + hand (`sim_backend.SimExecutor`);
  the reply is the final `ExecutionState`: status "done", "stopped" (e-stop or lost lease), or
  "refused" with a message naming the broken limit, joint and time. The worker's own job key does
  not execute commands (anyone on the bus may query it); it serves health queries and EStop.
- The command's `lease_token` must be a live liveliness token of the commander; its loss stops the
  motion (`safety.LeaseWatch`).
- `EStop` (as a job, or published on `safety.ESTOP_KEY`) stops every robot at once and latches:
  later commands are refused until the bridge restarts (the operator's deliberate action).
- A command with a `world` first resets the simulation to it (object, obstacles, robot at home);
  without one the plan runs in the world the previous command left (multi-step pushes).
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

from services.robot_bridge.safety import (
    COMMAND_KEY,
    EStopLatch,
    LeaseWatch,
    SafeExecutor,
    SafetyRefusal,
    check_lease_key,
    lease_alive,
)
from services.robot_bridge.hardware import HardwareSpec, connect_all
from services.robot_bridge.sim_backend import SimBackend, SimExecutor, StatePublisher
from shared.bus import BusConfig, OpenCancelled, Worker, open_session
from shared.bus.keys import ROBOT_STATE_KEY
from shared.codec import CodecError, decode, encode
from shared.messages import EStop, ErrorReply, ExecutionCommand, ExecutionState, Message, SimWorld
from shared.object_refs import load_object_ref
from shared.objects import ObjectLoadError, write_object_urdf
from shared.push_outcome import pose_matrix

SERVICE = "robot_bridge"
STATE_KEY = ROBOT_STATE_KEY

log = logging.getLogger("gd2p.robot_bridge")


class Bridge:
    """One simulated robot per (arm, hand), built on first use, behind lease and e-stop checks."""

    def __init__(self, session: zenoh.Session, publish: StatePublisher | None = None, lease_timeout_s: float = 1.0):
        self.session = session
        self.publish = publish
        self.lease_timeout_s = lease_timeout_s
        self.estop_latch = EStopLatch(session, [])
        self._executors: dict[tuple[str, str], SimExecutor] = {}
        self._lock = threading.Lock()
        self.hardware: SafeExecutor | None = None  # set by `attach_hardware`; then no simulated robot is used

    def attach_hardware(self, spec: HardwareSpec) -> None:
        """Connect the real arm and hand (all or none) and route every command to them."""
        devices = spec.devices()
        connect_all(devices)
        self.hardware = SafeExecutor(self.session, spec.arm, spec.hand, devices, publish=self.publish,
                                     estop=self.estop_latch)

    def executor(self, arm: str, hand: str) -> SimExecutor:
        with self._lock:
            if (arm, hand) not in self._executors:
                backend = SimBackend(arm, hand, publish=self.publish)
                backend.connect()
                self.estop_latch.backends.append(backend)
                self._executors[(arm, hand)] = SimExecutor(backend)
            return self._executors[(arm, hand)]

    def execute(self, command: ExecutionCommand) -> ExecutionState:
        """Run `command.plan` if every check passes; the final state (or the refusal)."""
        if self.hardware is not None:
            return self.hardware.execute(command)  # its own lease, e-stop, limit and workspace checks
        executor = self.executor(command.plan.arm, command.plan.hand)
        try:
            self._check_command(command)
        except SafetyRefusal as exc:
            log.warning("refused command %s: %s", command.id, exc)
            return executor.backend.execution_state("refused", command.id, str(exc))
        if command.world is not None:
            try:
                reset_world(executor.backend, command.world)
            except ObjectLoadError as exc:
                return executor.backend.execution_state("refused", command.id, f"world: {exc}")
        stop = threading.Event()
        with LeaseWatch(self.session, command.lease_token, on_lost=stop.set):
            state = executor.execute(command.plan, command.realtime_factor, command.id, stop)
        if state.status == "refused":
            log.warning("refused command %s: %s", command.id, state.message)
        elif state.status == "stopped" and not self.estop_latch.triggered.is_set():
            executor.backend.recover()  # a lost lease is not a fault: ready for the next commander
            state = state.model_copy(update={"message": f"lease {command.lease_token!r} lost; {state.message}"})
        return state

    def _check_command(self, command: ExecutionCommand) -> None:
        if self.estop_latch.triggered.is_set():
            last = self.estop_latch.last
            raise SafetyRefusal("estop", f"e-stop is latched ({last.reason if last else 'e-stop'}); restart the bridge "
                                "to clear it")
        if not lease_alive(self.session, check_lease_key(command.lease_token), self.lease_timeout_s):
            raise SafetyRefusal("lease", f"lease {command.lease_token!r} is not alive: the commander holds no "
                                "liveliness token there")

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


def reset_world(backend: SimBackend, world: SimWorld) -> None:
    """A fresh simulation: robot at home with the hand open, the object at its pose, the obstacles."""
    obj = load_object_ref(world.object)
    backend.disconnect()
    backend.connect()
    backend.add_object(write_object_urdf(obj), pose_matrix(world.object_pose))
    backend.add_obstacles([(o.x, o.y, o.radius) for o in world.obstacles])


def run(cfg: BusConfig, worker_id: str | None = None, stop: threading.Event | None = None,
        hardware: HardwareSpec | None = None) -> None:
    """Serve the robot bridge until SIGTERM/SIGINT or `stop`, publishing states on `STATE_KEY`.

    `hardware` (None = the simulated robot) is connected before the worker registers, so a bridge
    whose devices are absent fails at start with the device's error instead of announcing itself.
    """
    try:
        session = open_session(cfg, stop=stop)
    except OpenCancelled:
        log.info("robot_bridge stopped before a router was reachable")
        return
    bridge = None
    try:
        publisher = session.declare_publisher(STATE_KEY)

        def publish(state: ExecutionState) -> None:
            payload, encoding = encode(state)
            publisher.put(payload, encoding=encoding)

        bridge = Bridge(session, publish)
        if hardware is not None:
            bridge.attach_hardware(hardware)
        commands = bridge.serve_commands()
        Worker(SERVICE, bridge.handlers(), cfg, worker_id, stop=stop, session=session).run()
        commands.undeclare()
        publisher.undeclare()
    finally:
        if bridge is not None:
            bridge.close()
        session.close()
