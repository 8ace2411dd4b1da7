"""Bus adapter of the robot_bridge service: decodes commands, hands them to the executor, publishes states.

- An `ExecutionCommand` queried on `bus_safety.COMMAND_KEY` (the one key the secure profile lets only
  the planner query) runs on the robot of the plan's arm + hand behind `executor.Executor`'s checks:
  the simulated robot (one per arm + hand, built on first use: PyBullet's `robots/sim`, or with `--robot
  mujoco` MuJoCo's `robots/mujoco`, an engine the planner's PyBullet rollouts are not), or with `--hardware
  ARM+HAND` the real devices (`hardware.HardwareSpec`), when a command for any other robot is
  refused and no simulated world is built. The reply is the final `ExecutionState`: status "done",
  "stopped" (e-stop or lost lease), "error", or "refused" with a message naming the broken limit, joint
  and time. The worker's own job key does not execute commands (anyone on the bus may query it); it
  serves health queries and EStop.
- The command's `lease_token` must be a planner's lease, `gd2p/lease/planner/<identity>/<holder>`, held by a live
  liveliness token (`bus_safety.CommandLease`). It is watched from before the first check until the
  motion ends: a lease lost at any point — during the checks, the world reset or the motion; the
  commander dropped it, or this bridge lost its router — refuses or stops the command, and the final
  state names the loss and how long the halt took. With a `probe` session (what `run` opens), a
  `RouterWatchdog` also notices a router that hangs without closing the link.
- Anything published on `bus_safety.ESTOP_KEY` (or an `EStop` job) stops every robot at once and latches:
  later commands are refused until the bridge restarts (the operator's deliberate action).
- A command with a `world` first resets the simulation to it (object, obstacles, robot at home);
  without one the plan runs in the world the previous command left (multi-step pushes). A command
  whose lease is lost during the reset is refused before anything moves.
- While a plan runs, `ExecutionState`s are published on `STATE_KEY` at the robot's state rate, with the
  plan time and the object's tracked pose. States and track frames go out through `RecordedPublisher`s
  (congestion control BLOCK, numbered for the recorder) with a send queue of their own
  (`PUBLISH_QUEUE`): the control loop that publishes them never waits on the bus, and a state that finds
  the queue full is dropped with its number, so the recorder counts it missing.
- The object's pose while a plan runs comes from a tracker on `TRACK_KEY` (ObjectTrack): the simulated
  robot's own tracker publishes there; with hardware, a user's tracker does, and the bridge folds its
  latest pose (if under `TRACK_FRESH_S` old) into the states it publishes, where the planner's
  closed-loop monitor reads it.

- With confirm on (`--confirm`, the default with `--hardware`; `confirm_timeout_s` here), a command that
  passed every check before motion is held (`shared.execution.confirm.ConfirmGate`): its `PlanHeld` is
  published on `gd2p/robot_bridge/held` and it runs only when an operator confirms it on
  `gd2p/robot_bridge/confirm` (`bus_safety.ConfirmServer`; `gd2p confirm ID`, client/confirm.py) within the
  timeout; otherwise it is refused "not_confirmed: ..." (the planner answers ErrorReply "not_confirmed").
  The lease and the e-stop rules hold while it waits.

Each command runs on a thread of its own, so a second command is answered ("refused: busy") while
one executes (or waits for confirmation).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh

from services.robot_bridge.bus_safety import COMMAND_KEY, ConfirmServer, EStopSubscriber, LeasedExecutor
from shared.bus import STREAM_QUEUE, BusConfig, OpenCancelled, RecordedPublisher, Worker, open_session
from shared.bus.keys import OBJECT_TRACK_KEY, ROBOT_STATE_KEY
from shared.bus.lease import RouterWatchdog
from shared.contracts.codec import CodecError, decode, encode
from shared.contracts.messages import (
    ErrorReply,
    EStop,
    ExecutionCommand,
    ExecutionState,
    Message,
    ObjectPose,
    ObjectTrack,
)
from shared.execution.confirm import ConfirmGate
from shared.execution.executor import EStopLatch, Executor, StatePublisher
from shared.execution.hardware import HardwareSpec, connect_all
from shared.execution.limits import SafetyRefusal
from shared.execution.robots import SIM_ROBOTS, TRACKING_MODES, TrackingMode
from shared.execution.robots.sim.config import SimConfig
from shared.execution.robots.sim.robot import SimRobot

if TYPE_CHECKING:
    from shared.execution.robots.mujoco.robot import MujocoRobot

SERVICE = "robot_bridge"
STATE_KEY = ROBOT_STATE_KEY
TRACK_KEY = OBJECT_TRACK_KEY
TRACK_FRESH_S = 0.5  # an external tracker's pose older than this is not folded into the states
REMEMBERED_COMMANDS = 65_536  # command ids kept to refuse a replay (ids are uuid4: 2.5 MB at most)
PUBLISH_QUEUE = STREAM_QUEUE  # states (and track frames) waiting to be sent: 2 s at 500 Hz

log = logging.getLogger("gd2p.robot_bridge")


class TrackSubscriber:
    """The latest ObjectTrack a tracker outside the robots (a user's, on hardware) published on TRACK_KEY."""

    def __init__(self, session: zenoh.Session):
        self._latest: tuple[float, ObjectPose] | None = None
        self._subscriber = session.declare_subscriber(TRACK_KEY, self._on_track)

    def _on_track(self, sample: zenoh.Sample) -> None:  # zenoh callback: quick
        try:
            track = decode(sample.payload.to_bytes(), str(sample.encoding), ObjectTrack)
        except CodecError:
            return
        if isinstance(track, ObjectTrack):
            self._latest = (time.monotonic(), track.pose)

    def latest(self) -> ObjectPose | None:
        """The last pose received, unless it is older than TRACK_FRESH_S."""
        latest = self._latest
        return latest[1] if latest is not None and time.monotonic() - latest[0] <= TRACK_FRESH_S else None

    def close(self) -> None:
        self._subscriber.undeclare()


class Bridge:
    """One simulated robot per (arm, hand), built on first use, or the attached hardware, each behind an
    executor; commands are leased on this session, and the e-stop key engages one latch for all.

    `probe`: a second session to the same router; with it a `RouterWatchdog` stops motion when the
    router stops forwarding (hung, or a link that drops packets without closing). The caller keeps
    both sessions.

    `confirm_timeout_s` (None = confirm off): hold every command that passed its checks until an operator
    confirms it, at most this long (`ConfirmGate`).

    `robot`: the simulated robots' engine, "sim" (PyBullet) or "mujoco"; `tracking`: how they see the object while a
    plan runs, "image" (registered in the depth frames they render, as a real robot's cameras would) or "truth"
    (the simulator's pose with a little noise: quicker, for work on the planner, never for a figure).
    """

    def __init__(self, session: zenoh.Session, publish: StatePublisher | None = None, lease_timeout_s: float = 1.0,
                 probe: zenoh.Session | None = None, publish_track: Callable[[ObjectTrack], None] | None = None,
                 confirm_timeout_s: float | None = None, robot: str = "sim", tracking: TrackingMode = "image"):
        if robot not in SIM_ROBOTS:
            raise ValueError(f"unknown simulated robot {robot!r}; known: {', '.join(SIM_ROBOTS)}")
        if tracking not in TRACKING_MODES:
            raise ValueError(f"unknown tracking {tracking!r}; known: {', '.join(TRACKING_MODES)}")
        self.robot = robot
        self.tracking = tracking
        self.session = session
        self.publish = publish
        self.publish_track = publish_track  # the simulated robots' tracker frames
        self.tracks: TrackSubscriber | None = None  # with hardware: a user's tracker
        self.lease_timeout_s = lease_timeout_s
        self.estop_latch = EStopLatch()
        self._estop_subscriber = EStopSubscriber(session, self.estop_latch)
        self.confirm_gate = (ConfirmGate(self.estop_latch, confirm_timeout_s) if confirm_timeout_s is not None
                             else None)
        self._confirm_server = ConfirmServer(session, self.confirm_gate) if self.confirm_gate is not None else None
        self.watchdog = (RouterWatchdog(session, probe, f"{SERVICE}-{session.zid()}") if probe is not None
                         else None)
        self._executors: dict[tuple[str, str], LeasedExecutor] = {}
        self._lock = threading.Lock()
        self.hardware: LeasedExecutor | None = None  # set by `attach_hardware`; then no simulated robot is used
        # Command ids this bridge has been asked to run: a command heard again (a replayed query, a
        # retry after a lost reply) is refused, whatever the arm has done since.
        self._seen_commands: OrderedDict[str, None] = OrderedDict()

    def _leased(self, executor: Executor) -> LeasedExecutor:
        if self.confirm_gate is not None:
            executor.hold = self.confirm_gate.hold
        return LeasedExecutor(self.session, executor, watchdog=self.watchdog, lease_timeout_s=self.lease_timeout_s)

    def attach_hardware(self, spec: HardwareSpec) -> None:
        """Connect the real arm and hand (all or none) and route every command to them."""
        robots = spec.robots()
        connect_all(robots)
        self.tracks = TrackSubscriber(self.session)
        self.hardware = self._leased(Executor(spec.arm, spec.hand, robots, self.estop_latch, publish=self.publish,
                                              tracked_object=self.tracks.latest))

    def executor(self, arm: str, hand: str) -> LeasedExecutor:
        """The simulated robot of `arm` + `hand` behind its executor (built and connected on first use)."""
        with self._lock:
            if (arm, hand) not in self._executors:
                robot = self._simulated_robot(arm, hand)
                robot.track = self.publish_track
                robot.connect()
                executor = Executor(arm, hand, [robot], self.estop_latch, publish=self.publish,
                                    reset_world=robot.reset_told)
                self._executors[(arm, hand)] = self._leased(executor)
            return self._executors[(arm, hand)]

    def _simulated_robot(self, arm: str, hand: str) -> SimRobot | MujocoRobot:
        if self.robot == "mujoco":
            # Imported on first use: a PyBullet bridge never loads MuJoCo.
            from shared.execution.robots.mujoco.config import MujocoConfig
            from shared.execution.robots.mujoco.robot import MujocoRobot

            return MujocoRobot(MujocoConfig(arm, hand, tracking=self.tracking), publish=self.publish)
        return SimRobot(SimConfig(arm, hand, tracking=self.tracking), publish=self.publish)

    def execute(self, command: ExecutionCommand) -> ExecutionState:
        """Run `command.plan` if every check passes, watching its lease throughout; the final state (or the refusal).
        A command id heard before is refused: a command runs at most once."""
        executor = self.hardware or self.executor(command.plan.arm, command.plan.hand)
        if not self._first_time(command.id):
            return executor.executor.refuse(command, SafetyRefusal(
                "replay", f"command {command.id} was received before; a command runs at most once (send a new id)"))
        return executor.execute(command)

    def _first_time(self, command_id: str) -> bool:
        with self._lock:
            if command_id in self._seen_commands:
                return False
            self._seen_commands[command_id] = None
            while len(self._seen_commands) > REMEMBERED_COMMANDS:
                self._seen_commands.popitem(last=False)
            return True

    def estop(self, request: EStop) -> ExecutionState:
        """Stop every robot now and latch; the reply is the state of the first robot (if any)."""
        self.estop_latch.engage(request)
        with self._lock:
            executors = [self.hardware] if self.hardware is not None else list(self._executors.values())
        message = f"e-stop: {request.reason}"
        if not executors:
            return ExecutionState(stamp=time.time(), joint_names=[], positions=np.zeros(0), velocities=np.zeros(0),
                                  status="stopped", command_id=request.id, message=f"{message} (no robot was moving)")
        return executors[0].executor.state("stopped", request.id, message)

    def close(self) -> None:
        self._estop_subscriber.close()
        if self._confirm_server is not None:
            self._confirm_server.close()
        if self.tracks is not None:
            self.tracks.close()
        if self.watchdog is not None:
            self.watchdog.close()
        with self._lock:
            executors = [*([self.hardware] if self.hardware is not None else []), *self._executors.values()]
            self.hardware = None
            self._executors.clear()
        for leased in executors:
            for robot in leased.executor.robots:
                robot.disconnect()

    def handlers(self) -> dict[type[Message], Callable[[Any], Message]]:
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
        hardware: HardwareSpec | None = None, confirm_timeout_s: float | None = None, robot: str = "sim",
        tracking: TrackingMode = "image") -> None:
    """Serve the robot bridge until SIGTERM/SIGINT or `stop`, publishing states on `STATE_KEY`; with
    `confirm_timeout_s`, each command waits for an operator's confirmation (`Bridge`); `robot`: the
    simulated robot's engine ("sim": PyBullet, "mujoco"); `tracking`: how it sees the object ("image", "truth": Bridge).

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
        # Never a blocking put on the control loop (it stops the robot): a send queue of its own per key.
        publisher = RecordedPublisher(session, STATE_KEY, queue_size=PUBLISH_QUEUE)
        track_publisher = RecordedPublisher(session, TRACK_KEY, queue_size=PUBLISH_QUEUE)

        def publish(state: ExecutionState) -> None:
            payload, encoding = encode(state)
            publisher.put(payload, encoding=encoding)

        def publish_track(track: ObjectTrack) -> None:
            payload, encoding = encode(track)
            track_publisher.put(payload, encoding=encoding)

        bridge = Bridge(session, publish, probe=probe, publish_track=None if hardware is not None else publish_track,
                        confirm_timeout_s=confirm_timeout_s, robot=robot, tracking=tracking)
        if hardware is not None:
            bridge.attach_hardware(hardware)
        commands = bridge.serve_commands()
        Worker(SERVICE, bridge.handlers(), cfg, worker_id, stop=stop, session=session).run()
        commands.undeclare()
        publisher.close()
        track_publisher.close()
    except OpenCancelled:
        log.info("robot_bridge stopped while opening its watchdog session")
    finally:
        if bridge is not None:
            bridge.close()
        if probe is not None:
            probe.close()
        session.close()
