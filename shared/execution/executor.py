"""The safety executor: a command runs on one or more robots behind every check, with no bus in sight.

One `Executor` serves the simulated robot (the bus bridge's default and the evaluation's `LocalRobot`)
and the hardware robots (an arm + a hand) alike:

1. Before anything moves (`check`; a violation is a `SafetyRefusal` naming the check): the e-stop is
   not engaged; a command's world is set up (the simulated robot's reset; the lease must be held
   first); the plan is for this arm + hand; every waypoint, every segment's speed at the timing the
   joints will move (a device moves `realtime_factor` times faster, the simulated robot keeps the
   plan's physics timing: `Robot.time_scale`) and the flange and hand base are inside the limits
   (`limits.check_plan`); each device's configured effort cap is inside its effort limit; the plan
   starts where the robot is; last, the lease is held.
2. While the plan runs (`_supervise`, every 1/`state_rate_hz` s): a lost lease, an engaged e-stop, a
   measured effort over its limit (a protective stop, latched like an e-stop) or a failing device
   stops every robot. A stop that is not an e-stop leaves the robots recovered for the next command.
3. The outcome is an `ExecutionState`: "done", "stopped" (why, and for a lost lease how long the halt
   took after the loss was noticed), "error" or "refused".

With a `hold` (preview and confirm, `gd2p up --confirm`: confirm.py's `ConfirmGate.hold`), a command that
passed every check of 1. waits there for an operator's confirmation; a lost lease, an engaged e-stop or no
confirmation in time refuse it (nothing moves). Once confirmed, the e-stop, the start state and the lease
are checked again, then it runs; its final state names who confirmed it.

The lease and the e-stop are small interfaces. `Lease`: the bus adapter gives a command's Zenoh lease
(`bus_safety.CommandLease`), the evaluation a `LocalLease` its cancellation releases. `EmergencyStop`:
`EStopLatch` (here) stops every robot it guards and latches; the bus adapter's e-stop subscriber
(`bus_safety.EStopSubscriber`) engages it, and so does a protective stop.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from shared.contracts.messages import EStop, ExecutionCommand, ExecutionState, ExecutionStatus, ObjectPose, SimWorld
from shared.execution.limits import SafetyRefusal, check_plan, plan_limits
from shared.execution.robot import (
    ExecutionReport,
    JointTrajectory,
    MotionStopped,
    Observation,
    Robot,
    RobotError,
    TrajectoryError,
)
from shared.robots.robot_limits import DEFAULT_WORKSPACE, WorkspaceBox

log = logging.getLogger("gd2p.robot_bridge.executor")

START_TOLERANCE_RAD = 0.05  # a plan must start within this of the current joint positions
StatePublisher = Callable[[ExecutionState], None]


# ------------------------------------------------------------------------------------------ interfaces
class Lease(Protocol):
    """The commander's right to move the robot, watched from before the first check until the motion ends."""

    @property
    def lost(self) -> bool:
        """True once the lease is gone (it never comes back)."""

    @property
    def reason(self) -> str:
        """Why it was lost ("" while held)."""

    def require(self) -> None:
        """SafetyRefusal("lease") unless the lease is held now."""

    def on_lost(self, callback: Callable[[], None]) -> None:
        """Call `callback` once when the lease is lost (at once if it already is); any thread, must be quick."""


class EmergencyStop(Protocol):
    """Stops every robot it guards at once and latches until an operator resets it."""

    @property
    def engaged(self) -> bool: ...

    @property
    def reason(self) -> str: ...

    def reason_once_described(self) -> str:
        """`reason`, waiting briefly for the message of a stop that has just halted the motion."""

    def engage(self, msg: EStop) -> None:
        """Stop every guarded robot now, then latch."""

    def guard(self, robots: Iterable[Robot]) -> None:
        """Add robots that engage() must stop."""


# ------------------------------------------------------------------------------------------ in-process implementations
class LocalLease:
    """A lease held in this process until `release(reason)`: the evaluation's, released by its request's
    cancellation. Its loss stops the motion like a lost bus lease."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lost = threading.Event()
        self._reason = ""
        self._callbacks: list[Callable[[], None]] = []

    @property
    def lost(self) -> bool:
        return self._lost.is_set()

    @property
    def reason(self) -> str:
        return self._reason

    def release(self, reason: str = "released by its holder") -> None:
        with self._lock:
            if self._lost.is_set():
                return
            self._reason = reason
            self._lost.set()
            callbacks, self._callbacks = self._callbacks, []
        for callback in callbacks:
            callback()

    def require(self) -> None:
        if self.lost:
            raise SafetyRefusal("lease", f"the lease is gone ({self.reason})")

    def on_lost(self, callback: Callable[[], None]) -> None:
        with self._lock:
            if not self._lost.is_set():
                self._callbacks.append(callback)
                return
        callback()


DESCRIBE_WAIT_S = 0.2  # the longest a report of a halted motion waits for the e-stop's message


class EStopLatch:
    """Stops every robot it guards at once, then latches until `reset()` (an operator's deliberate action).

    The order matters: stopping starts first (a thread of its own that sets the latch, then calls each
    robot's stop() in parallel, so one slow device does not delay the others, and never on the caller's
    thread, which may be Zenoh's), the latch is set next, and only then is the stop described — the
    bus adapter's subscriber calls `stop_now()` before it even decodes what arrived.
    """

    def __init__(self, robots: Iterable[Robot] = ()):
        self.robots: list[Robot] = list(robots)
        self.triggered = threading.Event()
        self.last: EStop | None = None  # what the latest stop said (set after the stop has started)
        self.described = threading.Event()  # `last` holds the latest stop's message

    @property
    def engaged(self) -> bool:
        return self.triggered.is_set()

    @property
    def reason(self) -> str:
        """What the latest stop said (generic while the e-stop key's message is still being decoded)."""
        return self.last.reason if self.last is not None else "a message on the e-stop key"

    def guard(self, robots: Iterable[Robot]) -> None:
        self.robots.extend(robots)

    def engage(self, msg: EStop) -> None:
        """Stop every robot now and latch (also from a protective stop or a hardware button)."""
        self.stop_now()
        self.describe(msg)

    def stop_now(self) -> None:
        robots = list(self.robots)

        def stop() -> None:
            self.triggered.set()  # before any robot stops: whoever sees a motion stopped sees the latch
            stop_all(robots)

        threading.Thread(target=stop, name="estop", daemon=True).start()
        self.triggered.set()

    def reason_once_described(self, wait_s: float = DESCRIBE_WAIT_S) -> str:
        """`reason`, after waiting up to `wait_s` for the stop's message to be described: for a report made once
        the motion has halted (the stop itself never waits for the message), which a busy machine can reach
        before the engaging thread has described the stop."""
        self.described.wait(wait_s)
        return self.reason

    def describe(self, msg: EStop) -> None:
        self.last = msg
        self.described.set()
        log.warning("E-STOP: %s (issued by %s)", msg.reason, msg.issued_by or "unknown")

    def reset(self) -> None:
        """Operator action: clear the latch and let each robot recover."""
        for robot in self.robots:
            robot.recover()
        self.last = None
        self.described.clear()
        self.triggered.clear()


def stop_all(robots: Sequence[Robot]) -> None:
    """Call stop() on every robot in parallel and wait for all (errors are logged, never raised)."""
    def stop_one(robot: Robot) -> None:
        try:
            robot.stop()
        except Exception:  # a failing device must not prevent the others from stopping
            log.exception("stopping %s failed", getattr(robot, "name", robot))

    threads = [threading.Thread(target=stop_one, args=(r,), daemon=True) for r in robots]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=5.0)


# ------------------------------------------------------------------------------------------ executor
@dataclass
class _Watch:
    """One command's stop: set by a lost lease (noting when) or by the supervisor for any other reason."""

    stop: threading.Event = field(default_factory=threading.Event)
    lease_lost_at: float | None = None  # time.monotonic() when the loss was noticed

    def lease_lost(self) -> None:  # the lease's thread: quick
        self.lease_lost_at = time.monotonic()
        self.stop.set()


class Executor:
    """Runs ExecutionCommands for one arm + hand on `robots` (together they drive every joint) behind every
    check of the module docstring.

    `estop` guards the robots. `publish` gets an "executing" ExecutionState each supervisor tick, or, for
    a robot that publishes its own states while it moves (the simulated robot), the final state.
    `reset_world` sets up a command's world (the simulated robot's reset); without it a world is ignored
    (a real robot lives in the real world).
    """

    def __init__(self, arm: str, hand: str, robots: Sequence[Robot], estop: EmergencyStop, *,
                 workspace: WorkspaceBox | None = DEFAULT_WORKSPACE, T_world_base: np.ndarray | None = None,
                 start_tolerance_rad: float = START_TOLERANCE_RAD, state_rate_hz: float = 50.0,
                 publish: StatePublisher | None = None, reset_world: Callable[[SimWorld], None] | None = None,
                 tracked_object: Callable[[], ObjectPose | None] | None = None,
                 hold: Callable[[ExecutionCommand, Lease], str] | None = None):
        self.arm, self.hand = arm, hand
        self.robots = list(robots)
        self.limits = plan_limits(arm, hand, [r.limits for r in self.robots], workspace, T_world_base)
        uncovered = set(self.limits.joint_names) - {n for r in self.robots for n in r.joint_names}
        if uncovered:
            raise ValueError(f"no robot drives joints {sorted(uncovered)} of {arm} + {hand}")
        self.estop = estop
        self.estop.guard(self.robots)
        self.start_tolerance_rad = start_tolerance_rad
        self.state_period_s = 1.0 / state_rate_hz
        self.publish = publish
        self.reset_world = reset_world
        # Where a tracker outside the robots last saw the object (a user's tracker on hardware), for the
        # states of robots that do not see it themselves.
        self.tracked_object = tracked_object
        self._streams = any(r.streams_states for r in self.robots)
        self._busy = threading.Lock()
        # Preview and confirm: called after every check, before motion; returns who confirmed, or raises
        # SafetyRefusal (not confirmed in time, lease lost, e-stop) and nothing moves.
        self.hold = hold

    def execute(self, command: ExecutionCommand, lease: Lease) -> ExecutionState:
        """Check, then run every robot's part of the plan at once; stop all on lease loss, e-stop or effort."""
        if not self._busy.acquire(blocking=False):
            return self.state("refused", command.id, "busy: another command is executing")
        try:
            watch = _Watch()
            lease.on_lost(watch.lease_lost)
            trajectory = self.check(command, lease)
            confirmed = None
            if self.hold is not None:
                confirmed = f"confirmed by {self.hold(command, lease) or 'an unnamed operator'}"
                self._recheck(trajectory, lease)  # the wait may have been long: nothing may have changed
            state = self._run(command, trajectory, lease, watch)
            if confirmed is not None:
                state = state.model_copy(update={"message": "; ".join(m for m in (state.message, confirmed) if m)})
            if self._streams and self.publish is not None:
                self.publish(state)  # the last of the states the robot published while it moved
            return state
        except SafetyRefusal as exc:
            return self.refuse(command, exc)
        finally:
            self._busy.release()

    def refuse(self, command: ExecutionCommand, refusal: SafetyRefusal) -> ExecutionState:
        log.warning("refused command %s: %s", command.id, refusal)
        return self.state("refused", command.id, str(refusal))

    def check(self, command: ExecutionCommand, lease: Lease) -> JointTrajectory:
        """Every check that must pass before anything moves, the lease last; the plan's trajectory.
        Raises SafetyRefusal."""
        if self.estop.engaged:
            raise SafetyRefusal("estop", f"e-stop is latched ({self.estop.reason}); an operator must reset it "
                                "(restart the bridge) before commanding motion")
        if command.world is not None and self.reset_world is not None:
            lease.require()  # a lost lease costs no reset; one lost during the reset is refused below
            self.reset_world(command.world)
        plan = command.plan
        if (plan.arm, plan.hand) != (self.arm, self.hand):
            raise SafetyRefusal("plan", f"plan is for {plan.arm} + {plan.hand}; this robot is {self.arm} + {self.hand}")
        check_plan(self.limits, plan, max(r.time_scale(command.realtime_factor) for r in self.robots))
        for robot in self.robots:
            robot.limits.check_effort_cap(robot.effort_cap)
        try:
            trajectory = JointTrajectory.from_plan(plan)  # each robot runs it at its own timing (time_scale)
        except TrajectoryError as exc:
            raise SafetyRefusal("plan", str(exc)) from None
        for robot in self.robots:
            self._check_start(robot, trajectory)
        lease.require()
        return trajectory

    def _recheck(self, trajectory: JointTrajectory, lease: Lease) -> None:
        """The checks that can change while a plan waits for confirmation: the e-stop, the start, the lease."""
        if self.estop.engaged:
            raise SafetyRefusal("estop", f"e-stop is latched ({self.estop.reason}); the confirmed plan does not run")
        for robot in self.robots:
            self._check_start(robot, trajectory)
        lease.require()

    def _check_start(self, robot: Robot, trajectory: JointTrajectory) -> None:
        start = trajectory.select(robot.joint_names).positions[0]
        # A joint pushed past its limit (a finger pressed by the object) is where its motor holds it: at the
        # limit. A plan may start there; it may not start outside the limits (check_plan).
        current = np.clip(robot.observe().positions, robot.limits.lower, robot.limits.upper)
        gap = np.abs(current - start)
        if gap.max() > self.start_tolerance_rad:
            k = int(np.argmax(gap))
            raise SafetyRefusal("start", f"{robot.name} joint {robot.joint_names[k]} is at {current[k]:.4f} rad but "
                                f"the plan starts at {start[k]:.4f} rad (tolerance {self.start_tolerance_rad} rad)")

    def _run(self, command: ExecutionCommand, trajectory: JointTrajectory, lease: Lease, watch: _Watch) -> ExecutionState:
        stop = watch.stop  # set by a lease loss, and by the supervisor for any other reason to stop
        reasons: list[str] = []
        reports: dict[str, ExecutionReport | BaseException] = {}
        running = [len(self.robots)]
        finished = threading.Event()
        count = threading.Lock()

        def run(robot: Robot) -> None:
            try:
                reports[robot.name] = robot.send(trajectory, stop, realtime_factor=command.realtime_factor,
                                                 command_id=command.id)
            except MotionStopped as exc:  # stopped from outside (e-stop, lease): the supervisor names why
                reports[robot.name] = exc
                stop.set()
            except BaseException as exc:  # reported below; any failure stops the other robots too
                reports[robot.name] = exc
                if not stop.is_set():
                    reasons.append(f"{robot.name}: {exc}")
                    stop.set()
            finally:
                with count:
                    running[0] -= 1
                    if running[0] == 0:
                        finished.set()

        for robot in self.robots:
            threading.Thread(target=run, args=(robot,), name=f"exec-{robot.name}", daemon=True).start()
        self._supervise(command, finished, watch, reasons)
        from_outside: list[str] = []
        if stop.is_set():
            from_outside = self._stop_reasons(lease, watch, time.monotonic())
            reasons[:0] = from_outside or ([] if reasons else ["stopped"])
            if not self.estop.engaged:
                self._recover(reasons)  # a lease-loss stop is no device fault: ready for the next lease
        return self._outcome(command, reports, reasons, bool(from_outside))

    def _supervise(self, command: ExecutionCommand, finished: threading.Event, watch: _Watch, reasons: list[str]) -> None:
        """Until every robot is done, each state tick: stop all on lease loss, e-stop, an effort over its
        limit or a failing robot, and publish the state (unless the robots publish their own)."""
        stopped = False
        next_tick = started = time.monotonic()
        plan_rate = self.robots[0].time_scale(command.realtime_factor)  # plan seconds per wall second
        while not finished.is_set():
            observations = self._observe()
            if not stopped and (watch.stop.is_set() or self.estop.engaged or self._protective_stop(observations)):
                watch.stop.set()  # a failing robot (reason already recorded) halts the others too
                stop_all(self.robots)
                stopped = True
            if self.publish is not None and observations and not self._streams:
                self.publish(self.state("executing", command.id, "", observations,
                                        plan_time_s=(time.monotonic() - started) * plan_rate))
            next_tick += self.state_period_s
            finished.wait(max(0.0, next_tick - time.monotonic()))

    def _recover(self, reasons: list[str]) -> None:
        for robot in self.robots:
            try:
                robot.recover()
            except RobotError as exc:
                reasons.append(f"{robot.name}: recovery after the stop failed: {exc}")

    def _stop_reasons(self, lease: Lease, watch: _Watch, halted_at: float) -> list[str]:
        """Why the motion stopped from outside: the e-stop, the lost lease (none for a robot's own failure)."""
        why = []
        if self.estop.engaged:
            why.append(f"e-stop: {self.estop.reason_once_described()}")
        if lease.lost:
            noticed = watch.lease_lost_at if watch.lease_lost_at is not None else halted_at
            why.append(f"{lease.reason}; motion halted {max(0.0, halted_at - noticed):.3f} s after the loss was noticed")
        return why

    def _protective_stop(self, observations: Mapping[str, Observation]) -> str | None:
        """An effort over its limit (a collision, a jam) latches like an e-stop: an operator must look."""
        violation = self._effort_violation(observations)
        if violation is None:
            return None
        self.estop.engage(EStop(reason=f"protective stop: {violation}", issued_by="robot_bridge safety"))
        return f"protective stop: {violation}"

    def _effort_violation(self, observations: Mapping[str, Observation]) -> str | None:
        for robot in self.robots:
            observation = observations.get(robot.name)
            if observation is not None and robot.reports_effort:
                message = robot.limits.check_measured_effort(observation.efforts)
                if message:
                    return message
        return None

    def _observe(self) -> dict[str, Observation]:
        """Every robot's observation now (one whose read fails is left out: its send() reports the link)."""
        observations = {}
        for robot in self.robots:
            try:
                observations[robot.name] = robot.observe()
            except RobotError:
                continue
        return observations

    def _outcome(self, command: ExecutionCommand, reports: Mapping[str, object], reasons: list[str],
                 stopped_from_outside: bool = False) -> ExecutionState:
        """The command's end. Stopped from outside (the e-stop, a lost lease), it is "stopped" whatever each device
        said: a device the stop reached before its motion began refuses to start ("stopped; call recover()"),
        which on a busy machine can happen, and is the stop's doing, not a fault (its words stay in the message)."""
        failures = {name: r for name, r in reports.items() if isinstance(r, BaseException)}
        if reasons and (stopped_from_outside or all(isinstance(r, MotionStopped) or not isinstance(r, BaseException)
                                                    for r in reports.values())):
            stopped = [str(r) for r in reports.values() if isinstance(r, MotionStopped)]
            return self.state("stopped", command.id, "; ".join([*reasons, *stopped]))
        if failures:
            return self.state("error", command.id, "; ".join(f"{n}: {e}" for n, e in failures.items()))
        finished = [r for r in reports.values() if isinstance(r, ExecutionReport)]
        short = [f"{r.device}: {r.message}" for r in finished if not r.completed]
        if short:  # a device fell short of its goal
            return self.state("error", command.id, "; ".join(short))
        return self.state("done", command.id, "; ".join(r.message for r in finished if r.message))

    def state(self, status: ExecutionStatus, command_id: str | None, message: str,
              observations: Mapping[str, Observation] | None = None, plan_time_s: float | None = None) -> ExecutionState:
        """The robots' joint state (and the object pose, if one observes it or a tracker saw it) with `status`
        and `message`."""
        names: list[str] = []
        positions: list[float] = []
        velocities: list[float] = []
        object_pose, object_lost = None, None
        for observation in (observations if observations is not None else self._observe()).values():
            names.extend(observation.joint_names)
            positions.extend(observation.positions.tolist())
            velocities.extend(observation.velocities.tolist())
            object_pose = object_pose or observation.object_pose
            object_lost = object_lost or observation.object_lost
        if object_pose is None and self.tracked_object is not None:
            object_pose = self.tracked_object()
        return ExecutionState(stamp=time.time(), joint_names=names, positions=np.asarray(positions, dtype=np.float64),
                              velocities=np.asarray(velocities, dtype=np.float64), object_pose=object_pose,
                              object_lost=None if object_pose is not None else object_lost,
                              status=status, command_id=command_id, message=message, plan_time_s=plan_time_s)
