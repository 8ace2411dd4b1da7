"""Safety of the robot bridge: limits checked before anything moves, the commander's lease, the e-stop.

1. Limits: each device's joint position, velocity and effort limits (`DeviceLimits`: the real device's
   numbers, e.g. the FR3's rather than the Panda model's), merged into limits.py's `RobotLimits` (the
   checks shared with the simulated robot) by `hardware_limits`: every waypoint inside the position
   limits, every segment's speed at the command's realtime factor inside the velocity limits, the
   flange and the hand base inside the workspace box along the densified path (`check_plan`). Here
   too: the plan must start where the robot is, and each device's configured effort cap (current /
   torque) must be inside its effort limit. A violation raises `SafetyRefusal` before anything moves.
2. Lease: a command carries `lease_token`, the key of the commander's Zenoh liveliness token. A
   command whose token is not alive is refused; while it executes the bridge watches the token, and
   its disappearance (the commander crashed, lost the network or closed its session) stops motion.
3. E-stop: an `EStop` message on `ESTOP_KEY` stops every backend at once and latches: commands are
   refused until `EStopLatch.reset()` (an operator's deliberate action; `recover()` on each backend).
   A measured effort over its limit during execution (a collision, a jam) is a protective stop that
   latches the same way.

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
from services.robot_bridge.limits import (
    DEFAULT_WORKSPACE,
    WORKSPACE_STEP_RAD,
    LimitViolation,
    RobotLimits,
    WorkspaceBox,
    densify,
)
from shared.codec import CodecError, decode
from shared.bus.keys import LEASE_PREFIX, ROBOT_COMMAND_KEY, ROBOT_ESTOP_KEY
from shared.messages import EStop, ExecutionCommand, ExecutionState, Plan

log = logging.getLogger("gd2p.robot_bridge.safety")

ESTOP_KEY = ROBOT_ESTOP_KEY
COMMAND_KEY = ROBOT_COMMAND_KEY
LEASE_PREFIX = LEASE_PREFIX  # commanders' liveliness tokens: gd2p/lease/<commander id>


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
DEVICE_LIMITS: dict[str, DeviceLimits] = {l.device: l for l in (FR3_LIMITS, XARM7_LIMITS, LEAP_LIMITS, ALLEGRO_LIMITS)}


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
def lease_key(commander_id: str) -> str:
    """Where a commander declares its lease token (the secure profile's ACL opens `gd2p/lease/**`)."""
    return check_lease_key(f"{LEASE_PREFIX}/{commander_id}")


def check_lease_key(token: str) -> str:
    """A lease token must be one concrete key (no wildcards: a pattern could match someone else's token)."""
    if not token or any(c in token for c in "*$?#") or token.startswith("/") or token.endswith("/") or "//" in token:
        raise SafetyRefusal("lease", f"lease token {token!r} is not a concrete key expression")
    try:
        zenoh.KeyExpr(token)
    except zenoh.ZError as exc:
        raise SafetyRefusal("lease", f"lease token {token!r} is not a valid key: {exc}") from None
    return token


def lease_alive(session: zenoh.Session, token: str, timeout_s: float = 1.0) -> bool:
    """True if a liveliness token is currently declared on exactly `token`."""
    check_lease_key(token)
    for reply in session.liveliness().get(token, timeout=timeout_s):
        if reply.ok is not None and str(reply.ok.key_expr) == token:
            return True
    return False


class LeaseWatch:
    """Watch a liveliness token; `lost` is set when it disappears. Use as a context manager."""

    def __init__(self, session: zenoh.Session, token: str, on_lost: Callable[[], None] | None = None):
        self.token = check_lease_key(token)
        self.lost = threading.Event()
        self._on_lost = on_lost
        self._subscriber = session.liveliness().declare_subscriber(self.token, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh callback thread: set events only
        if sample.kind == zenoh.SampleKind.DELETE:
            self.lost.set()
            if self._on_lost is not None:
                self._on_lost()

    def close(self) -> None:
        self._subscriber.undeclare()

    def __enter__(self) -> "LeaseWatch":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------------------ e-stop
class EStopLatch:
    """Subscribes to ESTOP_KEY; an EStop message stops every registered backend at once and latches.

    Stopping runs on a thread of its own (never in Zenoh's callback); each backend's stop() is called
    in parallel so one slow device does not delay the others.
    """

    def __init__(self, session: zenoh.Session, backends: Sequence[Backend]):
        self.backends = list(backends)
        self.triggered = threading.Event()
        self.last: EStop | None = None
        self._subscriber = session.declare_subscriber(ESTOP_KEY, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), str(sample.encoding), EStop)
        except CodecError as exc:
            # Anything on the e-stop key is treated as a stop: a malformed stop must still stop.
            msg = EStop(reason=f"undecodable e-stop message ({exc})")
        self.trigger(msg)

    def trigger(self, msg: EStop) -> None:
        """Stop every backend now and latch (also usable locally, e.g. from a hardware button)."""
        self.last = msg
        self.triggered.set()
        log.warning("E-STOP: %s (issued by %s)", msg.reason, msg.issued_by or "unknown")
        threading.Thread(target=stop_all, args=(self.backends,), name="estop", daemon=True).start()

    def reset(self) -> None:
        """Operator action: clear the latch and let each backend recover."""
        for backend in self.backends:
            backend.recover()
        self.triggered.clear()

    def close(self) -> None:
        self._subscriber.undeclare()


def stop_all(backends: Sequence[Backend]) -> None:
    """Call stop() on every backend in parallel and wait for all (errors are logged, never raised)."""
    def stop_one(backend: Backend) -> None:
        try:
            backend.stop()
        except Exception:  # a failing device must not prevent the others from stopping
            log.exception("stopping %s failed", backend.name)

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

    While a plan runs it reads every device's state at `state_rate_hz`: efforts are checked against
    the limits and, if `publish` is given, an ExecutionState ("executing") is published each tick.
    Pass the service's `estop` latch to share it (its backends are added); otherwise one is created.
    """

    def __init__(self, session: zenoh.Session, arm: str, hand: str, devices: Sequence[Device],
                 workspace: WorkspaceBox | None = DEFAULT_WORKSPACE, T_world_base: np.ndarray | None = None,
                 start_tolerance_rad: float = 0.05, lease_timeout_s: float = 1.0, state_rate_hz: float = 50.0,
                 publish: Callable[[ExecutionState], None] | None = None, estop: EStopLatch | None = None):
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
        self._owns_estop = estop is None
        self.estop = estop or EStopLatch(session, [])
        self.estop.backends.extend(d.backend for d in self.devices)
        self._busy = threading.Lock()

    def close(self) -> None:
        if self._owns_estop:
            self.estop.close()

    def check(self, command: ExecutionCommand) -> JointTrajectory:
        """Every check that must pass before anything moves; returns the trajectory. Raises SafetyRefusal."""
        if self.estop.triggered.is_set():
            reason = self.estop.last.reason if self.estop.last else "e-stop"
            raise SafetyRefusal("estop", f"e-stop is latched ({reason}); reset it before commanding motion")
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
        if not lease_alive(self.session, check_lease_key(command.lease_token), self.lease_timeout_s):
            raise SafetyRefusal("lease", f"lease {command.lease_token!r} is not alive: the commander holds no "
                                f"liveliness token there")
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
        """Check, then run every device's part of the plan at once; stop all on lease loss, e-stop or effort."""
        if not self._busy.acquire(blocking=False):
            return self._state(command, "refused", "busy: another command is executing")
        try:
            try:
                trajectory = self.check(command)
            except SafetyRefusal as exc:
                log.warning("refused command %s: %s", command.id, exc)
                return self._state(command, "refused", str(exc))
            return self._run(command, trajectory)
        finally:
            self._busy.release()

    def _run(self, command: ExecutionCommand, trajectory: JointTrajectory) -> ExecutionState:
        stop = threading.Event()
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

        with LeaseWatch(self.session, command.lease_token, on_lost=stop.set) as lease:
            threads = [threading.Thread(target=run, args=(d,), name=f"exec-{d.backend.name}", daemon=True)
                       for d in self.devices]
            for thread in threads:
                thread.start()
            self._supervise(command, threads, stop, lease, reasons)
        return self._outcome(command, reports, reasons)

    def _supervise(self, command: ExecutionCommand, threads: list[threading.Thread], stop: threading.Event,
                   lease: LeaseWatch, reasons: list[str]) -> None:
        """Until every device is done, each state tick: stop all on lease loss, e-stop or an effort over
        its limit, and publish the state."""
        stopped = False
        next_tick = time.monotonic()
        while any(t.is_alive() for t in threads):
            states = self._read_states()
            reason = self._stop_reason(lease) or self._protective_stop(states)
            if (reason or stop.is_set()) and not stopped:
                if reason:
                    reasons.append(reason)
                stop.set()  # a failing device (reason already recorded) halts the others too
                stop_all([d.backend for d in self.devices])
                stopped = True
            if self.publish is not None and states:
                self.publish(self._state(command, "executing", "", states))
            next_tick += self.state_period_s
            time.sleep(max(0.0, next_tick - time.monotonic()))
        if stop.is_set() and not reasons:  # the devices saw the stop before this loop did
            reasons.append(self._stop_reason(lease) or "stopped")
        if stop.is_set() and not self.estop.triggered.is_set():
            for device in self.devices:  # a lease-loss stop is no device fault: ready for the next lease
                try:
                    device.backend.recover()
                except BackendError as exc:
                    reasons.append(f"{device.backend.name}: recovery after the stop failed: {exc}")

    def _stop_reason(self, lease: LeaseWatch) -> str | None:
        if lease.lost.is_set():
            return f"lease {lease.token!r} lost"
        if self.estop.triggered.is_set():
            return f"e-stop: {self.estop.last.reason if self.estop.last else ''}"
        return None

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
