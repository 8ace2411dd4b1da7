"""The robot contract (in the style of LeRobot's `Robot`) shared by the simulated robot and every device.

A robot drives one device (an arm, a hand, or the simulated arm + hand) through the same calls:

    robot.connect()                                  open the link, configure the device (limits, modes)
    robot.observe()                                  Observation now; `observe_stream(rate_hz)` at a fixed rate
    report = robot.send(trajectory, stop)            follow a timed joint trajectory; blocks until it ends
    robot.stop()                                     halt motion now (from any thread); send() returns
    robot.recover()                                  clear device errors after a stop / fault
    robot.disconnect()

Each robot is built from its config dataclass (`robots/<name>/config.py`) and carries its device
limits (`limits.DeviceLimits`, read from its URDF). `executor.Executor` runs commands on one or more
robots behind the safety checks; nothing here knows of the bus.

Errors form one hierarchy so the bridge can tell the user what happened:

    RobotError
      DeviceUnavailable   the device is absent / unreachable / not connected (check cabling, IP, power)
      DeviceRefused       the device answered but refused (fault state, out of range, bad config)
      MotionStopped       send() ended early because of stop(), an e-stop or a lost lease

Joint order: a robot has its own `joint_names`; a `JointTrajectory` is re-ordered onto them with
`trajectory.select(robot.joint_names)`, so a plan of arm + hand joints feeds both devices.
"""
from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from shared.contracts.messages import ObjectPose, Plan

if TYPE_CHECKING:  # limits.py builds its SafetyRefusal on this module's errors
    from shared.execution.limits import DeviceLimits


class RobotError(RuntimeError):
    """Base of every robot error."""


class DeviceUnavailable(RobotError):
    """The device cannot be reached: not connected, absent, powered off, wrong address or port."""


class DeviceRefused(RobotError):
    """The device is reachable but refused a request (fault/protective stop, out of range, bad configuration)."""


class MotionStopped(RobotError):
    """send() was interrupted by stop(), an e-stop or a lost lease before the trajectory ended."""


class TrajectoryError(ValueError):
    """A joint trajectory is malformed (shapes, times, unknown joints)."""


@dataclass(frozen=True)
class JointTrajectory:
    """Joint positions [T, dof] (rad) at strictly increasing times [T] (s, from the start of motion)."""

    joint_names: tuple[str, ...]
    positions: np.ndarray
    times_s: np.ndarray

    def __post_init__(self) -> None:
        positions = np.asarray(self.positions, dtype=np.float64)
        times = np.asarray(self.times_s, dtype=np.float64)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "times_s", times)
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        if positions.ndim != 2 or positions.shape[1] != len(self.joint_names) or positions.shape[0] < 1:
            raise TrajectoryError(f"positions must be [T>=1, {len(self.joint_names)}], got {positions.shape}")
        if times.shape != (positions.shape[0],):
            raise TrajectoryError(f"times_s must have {positions.shape[0]} values, got shape {times.shape}")
        if not (np.isfinite(positions).all() and np.isfinite(times).all()):
            raise TrajectoryError("trajectory contains NaN or infinite values")
        if times[0] < 0 or np.any(np.diff(times) <= 0):
            raise TrajectoryError("times_s must start at >= 0 and increase strictly")

    @classmethod
    def from_plan(cls, plan: Plan, realtime_factor: float = 1.0) -> JointTrajectory:
        """All joints of a `shared.contracts.messages.Plan`; time is divided by `realtime_factor` (2 = twice as fast)."""
        if realtime_factor <= 0:
            raise TrajectoryError(f"realtime_factor must be > 0, got {realtime_factor}")
        return cls(tuple(plan.joint_names), plan.positions.to_numpy(), plan.times_s.to_numpy() / realtime_factor)

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1])

    @property
    def final(self) -> np.ndarray:
        return np.asarray(self.positions[-1])

    def scaled(self, realtime_factor: float) -> JointTrajectory:
        """The same path `realtime_factor` times faster (its times divided by the factor)."""
        if realtime_factor <= 0:
            raise TrajectoryError(f"realtime_factor must be > 0, got {realtime_factor}")
        return JointTrajectory(self.joint_names, self.positions, self.times_s / realtime_factor)

    def select(self, joint_names: Sequence[str]) -> JointTrajectory:
        """The columns of `joint_names`, in that order (TrajectoryError naming the missing ones)."""
        index = {name: i for i, name in enumerate(self.joint_names)}
        missing = [name for name in joint_names if name not in index]
        if missing:
            raise TrajectoryError(f"trajectory has no joints {missing}; it has {list(self.joint_names)}")
        columns = [index[name] for name in joint_names]
        return JointTrajectory(tuple(joint_names), self.positions[:, columns], self.times_s)

    def sample(self, t: float) -> np.ndarray:
        """Positions at time t (linear interpolation; held at the ends)."""
        times = self.times_s
        if t <= times[0]:
            return np.asarray(self.positions[0].copy())
        if t >= times[-1]:
            return np.asarray(self.positions[-1].copy())
        k = int(np.searchsorted(times, t, side="right")) - 1
        alpha = (t - times[k]) / (times[k + 1] - times[k])
        return np.asarray((1.0 - alpha) * self.positions[k] + alpha * self.positions[k + 1])

    def velocities(self) -> np.ndarray:
        """Finite-difference joint velocities [T-1, dof] between consecutive waypoints (rad/s)."""
        return np.diff(self.positions, axis=0) / np.diff(self.times_s)[:, None]


@dataclass(frozen=True)
class Observation:
    """What a robot observes: joint positions (rad), velocities (rad/s), efforts (Nm or mA) if measured,
    and the object's pose where the robot sees one (the simulated robot)."""

    stamp: float  # seconds since the Unix epoch
    joint_names: tuple[str, ...]
    positions: np.ndarray
    velocities: np.ndarray
    efforts: np.ndarray | None = None
    object_pose: ObjectPose | None = None
    object_lost: str | None = None  # why the robot's tracker sees no object pose now (an image tracker lost it)


@dataclass(frozen=True)
class ExecutionReport:
    """How a send() call ended."""

    device: str
    completed: bool
    final_positions: np.ndarray
    target_positions: np.ndarray
    duration_s: float
    message: str = ""
    samples: int = 0  # commands streamed to the device (0 for devices that interpolate themselves)

    @property
    def final_joint_error(self) -> float:
        """Largest absolute joint error at the end (rad)."""
        return float(np.max(np.abs(self.final_positions - self.target_positions)))


class Robot(ABC):
    """One device behind the connect / observe / send / disconnect contract (see the module docstring)."""

    name: str = "robot"
    state_rate_hz: float = 100.0
    reports_effort: bool = False  # observe() measures efforts, checked against `limits.effort` while moving
    # True for a robot that publishes its own states while it moves (the simulated robot: in its own clock,
    # with the object pose); the executor then publishes only the final state. Devices are sampled by it.
    streams_states: bool = False

    def __init__(self, joint_names: Sequence[str], limits: DeviceLimits):
        self.joint_names: tuple[str, ...] = tuple(joint_names)
        if self.joint_names != limits.joint_names:
            raise ValueError(f"{self.name}: joints {self.joint_names} differ from its limits' {limits.joint_names}")
        self.limits = limits
        # The effort cap the device is configured with (limits.effort_unit), None when the device has none
        # of its own; it must never exceed the limit.
        self.effort_cap: np.ndarray | None = None
        self._stop_requested = threading.Event()

    @property
    @abstractmethod
    def connected(self) -> bool:
        """True between a successful connect() and disconnect()."""

    @abstractmethod
    def connect(self) -> None:
        """Open the link and configure the device; DeviceUnavailable if it cannot be reached."""

    @abstractmethod
    def disconnect(self) -> None:
        """Leave the device safe (holding, torque as configured) and close the link. Idempotent."""

    @abstractmethod
    def observe(self) -> Observation:
        """What the robot observes now."""

    @abstractmethod
    def send(self, trajectory: JointTrajectory, stop: threading.Event | None = None, *, realtime_factor: float = 1.0,
             command_id: str | None = None) -> ExecutionReport:
        """Follow `trajectory` (this robot's joints, any order/superset; the plan's timing) `realtime_factor`
        times faster; raise MotionStopped if stopped. `command_id` stamps the states a robot publishes itself."""

    def time_scale(self, realtime_factor: float) -> float:
        """How many times faster than planned the joints move for a command's `realtime_factor` (what the
        velocity limits are checked at): a device moves that much faster."""
        return realtime_factor

    def stop(self) -> None:
        """Halt motion as fast as the device safely can; safe to call from any thread, any time."""
        self._stop_requested.set()

    def recover(self) -> None:
        """Clear a stop or a device fault so the next send() may run."""
        self._stop_requested.clear()

    def observe_stream(self, rate_hz: float | None = None, stop: threading.Event | None = None) -> Iterator[Observation]:
        """Observation at a fixed rate (default `state_rate_hz`) until `stop` is set; ticks never drift."""
        period = 1.0 / (rate_hz or self.state_rate_hz)
        next_tick = time.monotonic()
        while stop is None or not stop.is_set():
            yield self.observe()
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_tick = time.monotonic()  # fell behind: restart the schedule instead of bursting

    def require_connected(self) -> None:
        if not self.connected:
            raise DeviceUnavailable(f"{self.name}: not connected (call connect() first)")

    def _prepare_send(self, trajectory: JointTrajectory, realtime_factor: float) -> JointTrajectory:
        """The checks before a device moves; its joints of `trajectory` at the timing it will run."""
        self.require_connected()
        if self._stop_requested.is_set():
            raise DeviceRefused(f"{self.name}: stopped; call recover() before executing again")
        return trajectory.select(self.joint_names).scaled(realtime_factor)

    def _stopped(self, stop: threading.Event | None) -> bool:
        return self._stop_requested.is_set() or (stop is not None and stop.is_set())


class StreamingRobot(Robot):
    """A robot that streams interpolated position targets at `command_rate_hz` (LEAP, Allegro, xArm servo mode).

    Subclasses implement `_send_positions(q)` and `observe()`; `send` owns the timing loop, so stop,
    e-stop and lease loss are honoured within one command period.
    """

    def __init__(self, joint_names: Sequence[str], limits: DeviceLimits, command_rate_hz: float = 100.0,
                 settle_tolerance_rad: float = 0.02, settle_timeout_s: float = 1.0):
        super().__init__(joint_names, limits)
        self.command_rate_hz = command_rate_hz
        self.settle_tolerance_rad = settle_tolerance_rad
        self.settle_timeout_s = settle_timeout_s

    @abstractmethod
    def _send_positions(self, q: np.ndarray) -> None:
        """Command joint positions q (this robot's joint order, rad)."""

    def _halt(self) -> None:
        """Device-specific action on stop (default: hold the current measured position)."""
        self._send_positions(self.observe().positions)

    def stop(self) -> None:
        super().stop()
        if self.connected:
            try:
                self._halt()
            except RobotError:
                pass  # the send loop also stops streaming; a dead link cannot be commanded anyway

    def send(self, trajectory: JointTrajectory, stop: threading.Event | None = None, *, realtime_factor: float = 1.0,
             command_id: str | None = None) -> ExecutionReport:
        own = self._prepare_send(trajectory, realtime_factor)
        period = 1.0 / self.command_rate_hz
        start = time.monotonic()
        samples = 0
        while True:
            if self._stopped(stop):
                self._halt()
                raise MotionStopped(f"{self.name}: stopped {time.monotonic() - start:.2f} s into a "
                                    f"{own.duration_s:.2f} s trajectory")
            t = time.monotonic() - start
            try:
                self._send_positions(own.sample(t))
            except RobotError:
                if self._stopped(stop):  # stop() halted the device between our check and this command
                    raise MotionStopped(f"{self.name}: stopped {t:.2f} s into a {own.duration_s:.2f} s trajectory") from None
                raise
            samples += 1
            if t >= own.duration_s:
                break
            time.sleep(max(0.0, start + samples * period - time.monotonic()))
        final = self._settle(own.final, stop)
        error = float(np.max(np.abs(final - own.final)))
        return ExecutionReport(self.name, error <= self.settle_tolerance_rad, final, own.final,
                               time.monotonic() - start,
                               "" if error <= self.settle_tolerance_rad else f"final joint error {error:.4f} rad",
                               samples)

    def _settle(self, target: np.ndarray, stop: threading.Event | None) -> np.ndarray:
        """Wait (up to settle_timeout_s) for the device to reach the final target; return where it ended."""
        deadline = time.monotonic() + self.settle_timeout_s
        positions = self.observe().positions
        while np.max(np.abs(positions - target)) > self.settle_tolerance_rad and time.monotonic() < deadline:
            if self._stopped(stop):
                self._halt()
                raise MotionStopped(f"{self.name}: stopped while settling on the final waypoint")
            time.sleep(1.0 / self.state_rate_hz)
            positions = self.observe().positions
        return positions
