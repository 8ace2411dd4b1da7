"""The arm `panda`: a Franka Research 3 over franky-control (libfranka protocol; franky-sim serves it on loopback).

Connect: franky.Robot(host) -> recover if the robot reports errors -> collision thresholds (the
external-torque reflex that halts the arm, per joint, from the effort cap) -> dynamics factor.
Motion: one JointWaypointMotion through every waypoint; each waypoint carries the plan's
finite-difference velocity (so the arm passes through instead of stopping) and the plan's segment
duration as its minimum time (Ruckig never runs ahead of the plan's timing; it may lag it when the
dynamics factor is small). It runs asynchronously so stop(), an e-stop or a lost lease interrupt it.
State: current joint positions/velocities and measured joint torques (tau_J, Nm).
Stop: robot.stop() (libfranka halts the motion generator). Recover: robot.recover_from_errors().
"""
from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from shared.execution.robot import (
    DeviceRefused,
    DeviceUnavailable,
    ExecutionReport,
    JointTrajectory,
    MotionStopped,
    Observation,
    Robot,
)
from shared.execution.robots.panda.config import PandaConfig, limits


def _franky() -> Any:
    try:
        import franky
    except ImportError:
        raise DeviceUnavailable("Franka: franky-control is not installed (pip install 'gd2p-zenoh[franka]')") from None
    return franky


class PandaRobot(Robot):
    """The FR3 of `config` (its joints named as the Panda model's: limits.joint_names)."""

    name = "panda"
    reports_effort = True

    def __init__(self, config: PandaConfig):
        device_limits = limits()
        super().__init__(device_limits.joint_names, device_limits)
        self.config = config
        self.host = config.host
        self.relative_dynamics_factor = config.relative_dynamics_factor
        self.effort_cap = np.asarray(config.collision_torque_nm, dtype=np.float64)  # reflex threshold per joint
        self.realtime = config.realtime
        self.settle_tolerance_rad = config.settle_tolerance_rad
        self.poll_period_s = config.poll_period_s
        self._robot: Any = None
        self._lock = threading.Lock()

    @property
    def connected(self) -> bool:
        return self._robot is not None

    def connect(self) -> None:
        if self.connected:
            return
        franky = _franky()
        config = franky.RealtimeConfig.Enforce if self.realtime else franky.RealtimeConfig.Ignore
        try:
            robot = franky.Robot(self.host, realtime_config=config)
        except Exception as exc:  # franky raises NetworkException / IncompatibleVersionException / RealtimeException
            raise DeviceUnavailable(f"Franka at {self.host}: cannot connect: {exc}") from None
        try:
            if robot.has_errors and not robot.recover_from_errors():
                raise DeviceRefused(f"Franka at {self.host}: reports errors that automatic recovery cannot clear")
            robot.set_collision_behavior(list(self.config.collision_torque_nm), [30.0] * 6)
            robot.relative_dynamics_factor = self.relative_dynamics_factor
        except franky.Exception as exc:
            raise DeviceRefused(f"Franka at {self.host}: configuration refused: {exc}") from None
        self._robot = robot

    def disconnect(self) -> None:
        if self._robot is None:
            return
        try:
            self._robot.stop()
        except Exception:
            pass  # the link may already be gone; dropping the Robot closes it
        self._robot = None

    def observe(self) -> Observation:
        self.require_connected()
        try:
            joint_state = self._robot.current_joint_state
            torques = np.asarray(self._robot.state.tau_J, dtype=np.float64)
        except Exception as exc:
            raise DeviceUnavailable(f"Franka at {self.host}: state read failed: {exc}") from None
        return Observation(time.time(), self.joint_names, np.asarray(joint_state.position, dtype=np.float64),
                           np.asarray(joint_state.velocity, dtype=np.float64), torques)

    def _motion(self, trajectory: JointTrajectory) -> Any:
        franky = _franky()
        q, t = trajectory.positions, trajectory.times_s
        velocity = np.gradient(q, t, axis=0) if len(q) > 2 else np.zeros_like(q)
        velocity[-1] = 0.0  # come to rest on the final waypoint
        waypoints = []
        for k in range(1, len(q)):
            duration_ms = max(1, int(round((t[k] - t[k - 1]) * 1000)))
            waypoints.append(franky.JointWaypoint(franky.JointState(q[k], velocity[k]),
                                                  minimum_time=franky.Duration(duration_ms)))
        return franky.JointWaypointMotion(waypoints)

    def send(self, trajectory: JointTrajectory, stop: threading.Event | None = None, *, realtime_factor: float = 1.0,
             command_id: str | None = None) -> ExecutionReport:
        own = self._prepare_send(trajectory, realtime_factor)
        franky = _franky()
        start = time.monotonic()
        try:
            self._robot.move(self._motion(own), asynchronous=True)
            while not self._robot.join_motion(timeout=self.poll_period_s):
                if self._stopped(stop):
                    self._halt()
                    raise MotionStopped(f"{self.name}: stopped {time.monotonic() - start:.2f} s into a "
                                        f"{own.duration_s:.2f} s trajectory")
        except franky.Exception as exc:
            if self._stopped(stop):
                # stop() from another thread preempts the motion; libfranka reports that as an exception
                raise MotionStopped(f"{self.name}: stopped {time.monotonic() - start:.2f} s into a "
                                    f"{own.duration_s:.2f} s trajectory") from None
            # reflexes (collision, joint limits) abort the motion on the robot side
            raise DeviceRefused(f"Franka at {self.host}: motion aborted: {exc}; call recover()") from None
        final = self._settled_positions()
        error = float(np.max(np.abs(final - own.final)))
        ok = error <= self.settle_tolerance_rad
        return ExecutionReport(self.name, ok, final, own.final, time.monotonic() - start,
                               "" if ok else f"final joint error {error:.4f} rad")

    def _settled_positions(self, timeout_s: float = 0.5, still_rad_s: float = 0.01) -> np.ndarray:
        """Positions once the arm has come to rest (the motion generator ends before the joints settle)."""
        deadline = time.monotonic() + timeout_s
        state = self.observe()
        while np.max(np.abs(state.velocities)) > still_rad_s and time.monotonic() < deadline:
            time.sleep(self.poll_period_s)
            state = self.observe()
        return state.positions

    def _halt(self) -> None:
        franky = _franky()
        try:
            self._robot.stop()
            self._robot.join_motion(timeout=2.0)
        except franky.Exception:
            pass  # a stopped motion surfaces as a ControlException: that is the expected outcome here

    def stop(self) -> None:
        super().stop()
        if self._robot is not None:
            self._halt()

    def recover(self) -> None:
        super().recover()
        self.require_connected()
        if self._robot.has_errors and not self._robot.recover_from_errors():
            raise DeviceRefused(f"Franka at {self.host}: automatic error recovery failed")
