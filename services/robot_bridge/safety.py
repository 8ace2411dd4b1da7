"""Safety of the robot bridge: limits checked before anything moves, the commander's lease, the e-stop.

1. Limits: each device's joint position, velocity and effort limits (`DeviceLimits`: the real device's
   numbers, e.g. the FR3's rather than the Panda model's), merged into limits.py's `RobotLimits` (the
   checks shared with the simulated robot) by `hardware_limits`: every waypoint inside the position
   limits, every segment's speed at the command's realtime factor inside the velocity limits, the
   flange and the hand base inside the workspace box along the densified path (`check_plan`). Here
   too: the plan must start where the robot is, and each device's configured effort cap (current /
   torque) must be inside its effort limit. A violation raises `SafetyRefusal` before anything moves.
2. Lease: a command carries `lease_token`, which must be a planner's lease key,
   `gd2p/lease/planner/<holder>` (shared/bus/lease.py); any other key is refused, even one with a live
   token behind it (another role's lease, a worker's `gd2p/alive/...` token, a wildcard).
   `CommandLease` watches it with a `LeaseMonitor` from *before* the first check until the motion
   ends: the lease must be confirmed held before anything moves, and its loss at any moment (the
   commander dropped it, crashed or closed its session; this bridge lost its router; the bridge's
   `RouterWatchdog` heard nothing through the router for its bound) stops motion. The final
   state names the loss and how long the halt took after it was noticed.
3. E-stop: anything published on `ESTOP_KEY` — a valid `EStop`, an empty payload, garbage, a wrong
   encoding, another message type — starts stopping every backend *before* it is decoded or logged,
   then latches: commands are refused until `EStopLatch.reset()` (an operator's deliberate action;
   `recover()` on each backend). A measured effort over its limit during execution (a collision, a
   jam) is a protective stop that latches the same way.

`SafeExecutor` ties the three together for the hardware backends: `execute(ExecutionCommand)` ->
`ExecutionState`. It is plain Python given a Zenoh session; the service adapts it to the bus.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import zenoh

from services.robot_bridge.backend import (
    Backend,
    BackendError,
    ExecutionReport,
    JointState,
    JointTrajectory,
    MotionStopped,
    TrajectoryError,
)
from shared.bus.keys import ROBOT_COMMAND_KEY, ROBOT_ESTOP_KEY
from shared.bus.lease import LeaseError, LeaseMonitor, RouterWatchdog, parse_lease_key
from shared.codec import decode
from shared.messages import EStop, ExecutionCommand, ExecutionState, Message, Plan
from shared.robot_limits import (
    DEFAULT_WORKSPACE,
    WORKSPACE_STEP_RAD,
    LimitViolation,
    RobotLimits,
    WorkspaceBox,
    densify,
)

log = logging.getLogger("gd2p.robot_bridge.safety")

ESTOP_KEY = ROBOT_ESTOP_KEY
COMMAND_KEY = ROBOT_COMMAND_KEY
COMMAND_LEASE_ROLE = "planner"  # the only role whose lease may command motion


class SafetyRefusal(BackendError):
    """A command was refused by a safety check before anything moved; `check` names which one."""

    def __init__(self, check: str, message: str):
        super().__init__(f"{check}: {message}")
        self.check = check


# ------------------------------------------------------------------------------------------ limits
@dataclass(frozen=True)
class DeviceLimits:
    """Per-joint limits of one device. `effort` is in `effort_unit` (what the device can cap: Nm or mA)."""

    device: str
    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    effort_unit: str = "Nm"

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        for name in ("lower", "upper", "velocity", "effort"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (n,):
                raise ValueError(f"{self.device}: {name} limits need {n} values, got shape {value.shape}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        if np.any(self.lower >= self.upper) or np.any(self.velocity <= 0) or np.any(self.effort <= 0):
            raise ValueError(f"{self.device}: limits must satisfy lower < upper and velocity, effort > 0")

    def check_effort_cap(self, cap: np.ndarray | None) -> None:
        """SafetyRefusal if the device is configured to allow more effort than its limit."""
        if cap is None:
            return
        cap = np.asarray(cap, dtype=np.float64)
        if (cap > self.effort).any():
            joint = int(np.argmax(cap - self.effort))
            raise SafetyRefusal("effort_limits", f"{self.device} joint {self.joint_names[joint]} is configured for "
                                f"{cap[joint]:g} {self.effort_unit}, above its limit {self.effort[joint]:g} {self.effort_unit}")

    def check_measured_effort(self, efforts: np.ndarray | None) -> str | None:
        """A message naming the first joint whose measured |effort| exceeds its limit, else None."""
        if efforts is None:
            return None
        over = np.abs(np.asarray(efforts, dtype=np.float64)) > self.effort
        if not over.any():
            return None
        joint = int(np.argmax(over))
        return (f"{self.device} joint {self.joint_names[joint]} effort {efforts[joint]:g} {self.effort_unit} "
                f"exceeds {self.effort[joint]:g}")


def _names(prefix: str, count: int, start: int = 1) -> tuple[str, ...]:
    return tuple(f"{prefix}{i}" for i in range(start, start + count))


# Franka Research 3 (franka_description fr3 joint limits; identical to franky-sim's assets/fr3.urdf).
# Plans name the arm's joints as the Panda model does (shared/arms.py), which has the same kinematic chain.
FR3_LIMITS = DeviceLimits(
    "fr3", _names("panda_joint", 7),
    lower=[-2.9007, -1.8361, -2.9007, -3.0770, -2.8763, 0.4398, -3.0508],
    upper=[2.9007, 1.8361, 2.9007, -0.1169, 2.8763, 4.6216, 3.0508],
    velocity=[2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26],
    effort=[87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0],
)
# UFactory xArm7 (xarm_description xarm7.urdf in example-robot-data; SDK reports torques in Nm).
XARM7_LIMITS = DeviceLimits(
    "xarm7", _names("joint", 7),
    lower=[-6.2832, -2.059, -6.2832, -0.19198, -6.2832, -1.69297, -6.2832],
    upper=[6.2832, 2.0944, 6.2832, 3.927, 6.2832, 3.14159, 6.2832],
    velocity=[3.14] * 7,
    effort=[50.0, 50.0, 30.0, 30.0, 30.0, 20.0, 20.0],
)
# LEAP hand (LEAP_Hand_Sim robot.urdf: velocity 8.48 rad/s). Effort is the Dynamixel goal-current cap in
# mA: current-based position mode never exceeds it. 550 mA is the LEAP authors' setting for the full hand.
LEAP_LIMITS = DeviceLimits(
    "leap", tuple(str(i) for i in range(16)),
    lower=[-1.047, -0.314, -0.506, -0.366] * 3 + [-0.349, -0.47, -1.20, -1.34],
    upper=[1.047, 2.23, 1.885, 2.042] * 3 + [2.094, 2.443, 1.90, 1.88],
    velocity=[8.48] * 16,
    effort=[550.0] * 16,
    effort_unit="mA",
)
# Allegro hand V5 (joint ranges of example-robot-data's allegro_right_hand.urdf). Effort: the V5 driver caps
# its torque command at +-240 (its CAN units, ~mA; AllegroHandDrv.cpp), which is what we monitor.
ALLEGRO_LIMITS = DeviceLimits(
    "allegro", tuple(f"joint_{i}.0" for i in range(16)),
    lower=[-0.47, -0.196, -0.174, -0.227] * 3 + [0.263, -0.105, -0.189, -0.162],
    upper=[0.47, 1.61, 1.709, 1.618] * 3 + [1.396, 1.163, 1.644, 1.719],
    velocity=[7.0] * 16,
    effort=[240.0] * 16,
    effort_unit="mA",
)
DEVICE_LIMITS: dict[str, DeviceLimits] = {d.device: d for d in (FR3_LIMITS, XARM7_LIMITS, LEAP_LIMITS, ALLEGRO_LIMITS)}


def hardware_limits(arm: str, hand: str, devices: Sequence[DeviceLimits], workspace: WorkspaceBox | None = DEFAULT_WORKSPACE,
                    T_world_base: np.ndarray | None = None) -> RobotLimits:
    """Plan-level limits of a hardware arm + hand: limits.RobotLimits from the URDFs (joint positions,
    velocities, the workspace box for the flange and the hand base) narrowed by each device's own
    limits where the real device is stricter (e.g. the FR3's joints 4 and 6 against the Panda model)."""
    limits = RobotLimits.for_robot(arm, hand, workspace=workspace, T_world_base=T_world_base)
    lower, upper, velocity = limits.lower.copy(), limits.upper.copy(), limits.velocity.copy()
    index = {name: i for i, name in enumerate(limits.joint_names)}
    for device in devices:
        for k, name in enumerate(device.joint_names):
            if name not in index:
                raise ValueError(f"{device.device} joint {name!r} is not a joint of {arm} + {hand}")
            i = index[name]
            lower[i] = max(lower[i], device.lower[k])
            upper[i] = min(upper[i], device.upper[k])
            velocity[i] = min(velocity[i], device.velocity[k])
    return replace(limits, lower=lower, upper=upper, velocity=velocity)


def check_plan(limits: RobotLimits, plan: Plan, realtime_factor: float = 1.0) -> None:
    """SafetyRefusal unless every waypoint, every segment's speed at `realtime_factor` (the timing the
    hardware will run) and the densified tool path are inside `limits`."""
    try:
        positions = limits.reorder(plan)
        times = plan.times_s.to_numpy().astype(np.float64) / realtime_factor
        limits.check_positions(positions, times)
        limits.check_velocities(positions, times)
        if limits.workspace is not None:
            limits.check_workspace(*densify(positions, times, WORKSPACE_STEP_RAD))
    except LimitViolation as exc:
        raise SafetyRefusal(exc.limit, str(exc)) from None


# ------------------------------------------------------------------------------------------ lease
def check_command_lease(key: str) -> str:
    """`key` if it is a planner's lease key, `gd2p/lease/planner/<holder>`; SafetyRefusal("lease") otherwise.

    Nothing else may keep a command alive, even with a live token behind it: a worker's `gd2p/alive/...`
    token, a client's lease, a wildcard. The key says nothing about who holds its token: Zenoh
    consolidates tokens declared twice on one key, so the bridge cannot count holders. Binding the
    lease to the planner is the secure profile's (only the planner's certificate may declare tokens
    under `gd2p/lease/planner/**`) and the planner's (a fresh key per command).
    """
    try:
        role, _ = parse_lease_key(key)
    except LeaseError as exc:
        raise SafetyRefusal("lease", f"{exc}; a command's lease must be "
                            f"gd2p/lease/{COMMAND_LEASE_ROLE}/<holder>") from None
    if role != COMMAND_LEASE_ROLE:
        raise SafetyRefusal("lease", f"lease {key!r} is a {role} lease; only a {COMMAND_LEASE_ROLE} lease "
                            f"(gd2p/lease/{COMMAND_LEASE_ROLE}/<holder>) may command motion")
    return key


class CommandLease:
    """One command's lease, watched from before its first check until its motion ends (a context manager).

    Construction refuses a key that is not a planner lease (`check_command_lease`); entering starts a
    `LeaseMonitor` (with the bridge's `RouterWatchdog`, if any). From then on a loss sets `stop`, the
    event every backend's execute() polls, and records when it was noticed. `require()` is the check
    before motion: the lease must be confirmed held within `confirm_timeout_s` and not lost since.
    """

    def __init__(self, session: zenoh.Session, key: str, *, watchdog: RouterWatchdog | None = None,
                 confirm_timeout_s: float = 1.0):
        self.key = check_command_lease(key)
        self.session, self.watchdog = session, watchdog
        self.confirm_timeout_s = confirm_timeout_s
        self.stop = threading.Event()
        self.noticed_at: float | None = None  # time.monotonic() when the loss was noticed
        self._monitor: LeaseMonitor | None = None

    def __enter__(self) -> CommandLease:
        self._monitor = LeaseMonitor(self.session, self.key, on_lost=self._on_lost, watchdog=self.watchdog)
        return self

    def __exit__(self, *exc) -> None:
        self._monitor.close()

    def _on_lost(self) -> None:  # the monitor's thread: quick
        self.noticed_at = time.monotonic()
        self.stop.set()

    @property
    def lost(self) -> bool:
        return self._monitor.lost.is_set()

    @property
    def reason(self) -> str:
        return self._monitor.reason

    def require(self) -> None:
        """SafetyRefusal("lease") unless the lease is confirmed held and not lost."""
        if not self._monitor.wait_confirmed(self.confirm_timeout_s) or self.lost:
            why = self.reason or f"not confirmed held within {self.confirm_timeout_s:g} s"
            raise SafetyRefusal("lease", f"lease {self.key!r} is not alive ({why}); the commander must hold "
                                "its liveliness token there")

    def stop_note(self, halted_at: float) -> str:
        """The loss and how long the halt took after it was noticed (for the final state's message)."""
        noticed = self.noticed_at if self.noticed_at is not None else halted_at
        return f"{self.reason}; motion halted {max(0.0, halted_at - noticed):.3f} s after the loss was noticed"


# ------------------------------------------------------------------------------------------ e-stop
class EStopLatch:
    """Subscribes to ESTOP_KEY: anything published there stops every registered backend, then latches.

    The order matters: stopping starts first (a thread of its own that sets the latch, then calls
    each backend's stop() in parallel, so one slow device does not delay the others, and never on
    Zenoh's callback thread), the latch is set next, and only then is the sample decoded and
    described — an empty payload, garbage, a wrong encoding or another message type stops the robot
    just like a valid `EStop`.
    """

    def __init__(self, session: zenoh.Session, backends: Sequence[Backend]):
        self.backends = list(backends)
        self.triggered = threading.Event()
        self.last: EStop | None = None  # what the latest stop said (set after the stop has started)
        self._subscriber = session.declare_subscriber(ESTOP_KEY, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh callback: stop first, describe after
        self._stop_and_latch()
        self._describe(describe_estop(sample))

    def trigger(self, msg: EStop) -> None:
        """Stop every backend now and latch (also usable locally, e.g. from a hardware button)."""
        self._stop_and_latch()
        self._describe(msg)

    def _stop_and_latch(self) -> None:
        backends = list(self.backends)

        def stop() -> None:
            self.triggered.set()  # before any backend stops: whoever sees a motion stopped sees the latch
            stop_all(backends)

        threading.Thread(target=stop, name="estop", daemon=True).start()
        self.triggered.set()

    def _describe(self, msg: EStop) -> None:
        self.last = msg
        log.warning("E-STOP: %s (issued by %s)", msg.reason, msg.issued_by or "unknown")

    def reason(self) -> str:
        """What the latest stop said (generic while its message is still being decoded)."""
        return self.last.reason if self.last is not None else "a message on the e-stop key"

    def reset(self) -> None:
        """Operator action: clear the latch and let each backend recover."""
        for backend in self.backends:
            backend.recover()
        self.last = None
        self.triggered.clear()

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


def stop_all(backends: Sequence[Backend]) -> None:
    """Call stop() on every backend in parallel and wait for all (errors are logged, never raised)."""
    def stop_one(backend: Backend) -> None:
        try:
            backend.stop()
        except Exception:  # a failing device must not prevent the others from stopping
            log.exception("stopping %s failed", getattr(backend, "name", backend))

    threads = [threading.Thread(target=stop_one, args=(b,), daemon=True) for b in backends]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=5.0)


# ------------------------------------------------------------------------------------------ executor
@dataclass
class Device:
    """A connected backend and its device limits."""

    backend: Backend
    limits: DeviceLimits


class SafeExecutor:
    """Executes ExecutionCommands for one arm + hand on hardware backends behind every check of this module.

    The command's lease is watched (`CommandLease`, with `watchdog` if given) from before the first
    check until every device has stopped. While a plan runs it reads every device's state at
    `state_rate_hz`: efforts are checked against the limits and, if `publish` is given, an
    ExecutionState ("executing") is published each tick. Pass the service's `estop` latch to share it
    (its backends are added); otherwise one is created.
    """

    def __init__(self, session: zenoh.Session, arm: str, hand: str, devices: Sequence[Device],
                 workspace: WorkspaceBox | None = DEFAULT_WORKSPACE, T_world_base: np.ndarray | None = None,
                 start_tolerance_rad: float = 0.05, lease_timeout_s: float = 1.0, state_rate_hz: float = 50.0,
                 publish: Callable[[ExecutionState], None] | None = None, estop: EStopLatch | None = None,
                 watchdog: RouterWatchdog | None = None):
        self.session = session
        self.arm, self.hand = arm, hand
        self.devices = list(devices)
        self.limits = hardware_limits(arm, hand, [d.limits for d in self.devices], workspace, T_world_base)
        uncovered = set(self.limits.joint_names) - {n for d in self.devices for n in d.backend.joint_names}
        if uncovered:
            raise ValueError(f"no device drives joints {sorted(uncovered)} of {arm} + {hand}")
        self.start_tolerance_rad = start_tolerance_rad
        self.lease_timeout_s = lease_timeout_s
        self.state_period_s = 1.0 / state_rate_hz
        self.publish = publish
        self.watchdog = watchdog
        self._owns_estop = estop is None
        self.estop = estop or EStopLatch(session, [])
        self.estop.backends.extend(d.backend for d in self.devices)
        self._busy = threading.Lock()

    def close(self) -> None:
        if self._owns_estop:
            self.estop.close()

    def check(self, command: ExecutionCommand, lease: CommandLease) -> JointTrajectory:
        """Every check that must pass before anything moves, the watched `lease` last; the trajectory.
        Raises SafetyRefusal."""
        if self.estop.triggered.is_set():
            raise SafetyRefusal("estop", f"e-stop is latched ({self.estop.reason()}); reset it before commanding "
                                "motion")
        plan = command.plan
        if (plan.arm, plan.hand) != (self.arm, self.hand):
            raise SafetyRefusal("plan", f"plan is for {plan.arm} + {plan.hand}; this bridge drives {self.arm} + {self.hand}")
        check_plan(self.limits, plan, command.realtime_factor)
        for device in self.devices:
            device.limits.check_effort_cap(getattr(device.backend, "effort_cap", None))
        try:
            trajectory = JointTrajectory.from_plan(plan, command.realtime_factor)  # the timing that will run
        except TrajectoryError as exc:
            raise SafetyRefusal("plan", str(exc)) from None
        for device in self.devices:
            self._check_start(device.backend, trajectory)
        lease.require()
        return trajectory

    def _check_start(self, backend: Backend, trajectory: JointTrajectory) -> None:
        start = trajectory.select(backend.joint_names).positions[0]
        current = backend.state().positions
        gap = np.abs(current - start)
        if gap.max() > self.start_tolerance_rad:
            k = int(np.argmax(gap))
            raise SafetyRefusal("start", f"{backend.name} joint {backend.joint_names[k]} is at {current[k]:.4f} rad but "
                                f"the plan starts at {start[k]:.4f} rad (tolerance {self.start_tolerance_rad} rad)")

    def execute(self, command: ExecutionCommand) -> ExecutionState:
        """Watch the lease, check, then run every device's part of the plan at once; stop all on lease
        loss, e-stop or effort."""
        if not self._busy.acquire(blocking=False):
            return self._state(command, "refused", "busy: another command is executing")
        try:
            with CommandLease(self.session, command.lease_token, watchdog=self.watchdog,
                              confirm_timeout_s=self.lease_timeout_s) as lease:
                trajectory = self.check(command, lease)
                return self._run(command, trajectory, lease)
        except SafetyRefusal as exc:
            log.warning("refused command %s: %s", command.id, exc)
            return self._state(command, "refused", str(exc))
        finally:
            self._busy.release()

    def _run(self, command: ExecutionCommand, trajectory: JointTrajectory, lease: CommandLease) -> ExecutionState:
        stop = lease.stop  # set by a lease loss, and below by any other reason to stop
        reasons: list[str] = []
        reports: dict[str, ExecutionReport | BaseException] = {}

        def run(device: Device) -> None:
            try:
                reports[device.backend.name] = device.backend.execute(trajectory, stop)
            except MotionStopped as exc:  # stopped from outside (e-stop, lease): the supervisor names why
                reports[device.backend.name] = exc
                stop.set()
            except BaseException as exc:  # reported below; any failure stops the other devices too
                reports[device.backend.name] = exc
                if not stop.is_set():
                    reasons.append(f"{device.backend.name}: {exc}")
                    stop.set()

        threads = [threading.Thread(target=run, args=(d,), name=f"exec-{d.backend.name}", daemon=True)
                   for d in self.devices]
        for thread in threads:
            thread.start()
        self._supervise(command, threads, lease, reasons)
        return self._outcome(command, reports, reasons)

    def _supervise(self, command: ExecutionCommand, threads: list[threading.Thread], lease: CommandLease,
                   reasons: list[str]) -> None:
        """Until every device is done, each state tick: stop all on lease loss, e-stop, an effort over its
        limit or a failing device, and publish the state. Then put why it stopped first in `reasons`."""
        stopped = False
        next_tick = time.monotonic()
        while any(t.is_alive() for t in threads):
            states = self._read_states()
            if not stopped and (lease.stop.is_set() or self.estop.triggered.is_set() or self._protective_stop(states)):
                lease.stop.set()  # a failing device (reason already recorded) halts the others too
                stop_all([d.backend for d in self.devices])
                stopped = True
            if self.publish is not None and states:
                self.publish(self._state(command, "executing", "", states))
            next_tick += self.state_period_s
            time.sleep(max(0.0, next_tick - time.monotonic()))
        if lease.stop.is_set():
            reasons[:0] = self._stop_reasons(lease, time.monotonic()) or ([] if reasons else ["stopped"])
        if lease.stop.is_set() and not self.estop.triggered.is_set():
            for device in self.devices:  # a lease-loss stop is no device fault: ready for the next lease
                try:
                    device.backend.recover()
                except BackendError as exc:
                    reasons.append(f"{device.backend.name}: recovery after the stop failed: {exc}")

    def _stop_reasons(self, lease: CommandLease, halted_at: float) -> list[str]:
        """Why the motion stopped from outside: the e-stop, the lost lease (none for a device's own failure)."""
        why = []
        if self.estop.triggered.is_set():
            why.append(f"e-stop: {self.estop.reason()}")
        if lease.lost:
            why.append(lease.stop_note(halted_at))
        return why

    def _protective_stop(self, states: Mapping[str, JointState]) -> str | None:
        """An effort over its limit (a collision, a jam) latches like an e-stop: an operator must look."""
        violation = self._effort_violation(states)
        if violation is None:
            return None
        self.estop.trigger(EStop(reason=f"protective stop: {violation}", issued_by="robot_bridge safety"))
        return f"protective stop: {violation}"

    def _effort_violation(self, states: Mapping[str, JointState]) -> str | None:
        for device in self.devices:
            state = states.get(device.backend.name)
            if state is not None and getattr(device.backend, "reports_effort", False):
                message = device.limits.check_measured_effort(state.efforts)
                if message:
                    return message
        return None

    def _read_states(self) -> dict[str, JointState]:
        """Every device's state now (a device whose read fails is left out: its execute() reports the link)."""
        states = {}
        for device in self.devices:
            try:
                states[device.backend.name] = device.backend.state()
            except BackendError:
                continue
        return states

    def _outcome(self, command: ExecutionCommand, reports: Mapping[str, object], reasons: list[str]) -> ExecutionState:
        failures = {name: r for name, r in reports.items() if isinstance(r, BaseException)}
        if reasons and all(isinstance(r, MotionStopped) or not isinstance(r, BaseException) for r in reports.values()):
            return self._state(command, "stopped", "; ".join(reasons))
        if failures:
            return self._state(command, "error", "; ".join(f"{n}: {e}" for n, e in failures.items()))
        short = [f"{n}: {r.message}" for n, r in reports.items() if isinstance(r, ExecutionReport) and not r.completed]
        return self._state(command, "error" if short else "done", "; ".join(short))  # a device fell short of its goal

    def _state(self, command: ExecutionCommand, status: str, message: str,
               states: Mapping[str, JointState] | None = None) -> ExecutionState:
        names: list[str] = []
        positions: list[float] = []
        velocities: list[float] = []
        for state in (states if states is not None else self._read_states()).values():
            names.extend(state.joint_names)
            positions.extend(state.positions.tolist())
            velocities.extend(state.velocities.tolist())
        return ExecutionState(stamp=time.time(), joint_names=names, positions=np.asarray(positions, dtype=np.float64),
                              velocities=np.asarray(velocities, dtype=np.float64), status=status,
                              command_id=command.id, message=message)
