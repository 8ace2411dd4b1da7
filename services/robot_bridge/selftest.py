"""Hardware-adapter self-test without hardware: each adapter against a stand-in that speaks its protocol.

    franky   FR3 adapter -> franky-control -> libfranka protocol -> franky-sim (MuJoCo) on 127.0.0.1
    xarm     xArm7 adapter -> xarm-python-sdk -> fake controller at the SDK's transport boundary
    leap     LEAP adapter -> dynamixel-sdk -> pty -> Protocol 2.0 responder (16 X-series motors)
    allegro  Allegro adapter -> python-can virtual bus -> simulated Allegro V5 hand

For each: connect, check the plan against the device's limits, execute a short trajectory and report
the final joint error, then interrupt a second trajectory with stop() (MotionStopped expected) and
recover(). `run_selftest()` returns {"franky": {"ok": bool, ...}, "xarm": ..., "leap": ..., "allegro": ...};
a missing optional package gives ok=false with the reason and the install command.
"""
from __future__ import annotations

import importlib.util
import threading
import time
import uuid
from collections.abc import Callable

import numpy as np

from services.robot_bridge.backend import Backend, BackendError, JointTrajectory, MotionStopped
from services.robot_bridge.safety import DEVICE_LIMITS, DeviceLimits

DEVICES: tuple[str, ...] = ("franky", "xarm", "leap", "allegro")
# The error a stand-in's first-order joints must settle within for ok=true (rad).
FINAL_ERROR_TOLERANCE_RAD = 0.02


class MissingPackage(RuntimeError):
    pass


def _require(*modules_and_packages: tuple[str, str]) -> None:
    missing = [package for module, package in modules_and_packages if importlib.util.find_spec(module) is None]
    if missing:
        raise MissingPackage(f"{', '.join(missing)} not installed (pip install {' '.join(missing)})")


def _trajectory(backend: Backend, limits: DeviceLimits, delta_rad: float, duration_s: float,
                steps: int = 6) -> JointTrajectory:
    """From where the device is, a straight joint-space move of +-delta on every joint, kept inside the limits."""
    start = backend.state().positions
    middle = (limits.lower + limits.upper) / 2
    direction = np.where(start < middle, 1.0, -1.0)  # move towards the middle of each range
    goal = np.clip(start + direction * delta_rad, limits.lower, limits.upper)
    alphas = np.linspace(0.0, 1.0, steps)
    trajectory = JointTrajectory(backend.joint_names, start + np.outer(alphas, goal - start), alphas * duration_s)
    speed = np.abs(trajectory.velocities()).max(axis=0)
    if (speed > limits.velocity).any():
        raise ValueError(f"self-test trajectory too fast for {limits.device}: {speed} rad/s")
    return trajectory


def exercise(backend: Backend, limits: DeviceLimits, delta_rad: float = 0.2, duration_s: float = 0.6) -> dict:
    """connect -> execute (final error) -> interrupted execute (stop) -> recover -> disconnect."""
    started = time.monotonic()
    backend.connect()
    try:
        report = backend.execute(_trajectory(backend, limits, delta_rad, duration_s))
        result = {
            "final_joint_error_rad": round(report.final_joint_error, 5),
            "execute_s": round(report.duration_s, 3),
            "commands_streamed": report.samples,
        }
        stop = threading.Event()
        timer = threading.Timer(duration_s / 3, stop.set)
        timer.start()
        try:
            backend.execute(_trajectory(backend, limits, delta_rad, duration_s), stop)
            result["stop_ok"] = False
        except MotionStopped:
            result["stop_ok"] = True
        finally:
            timer.cancel()
        backend.recover()
        state = backend.state()
        result["state_after_recover"] = [round(float(v), 4) for v in state.positions]
        result["ok"] = bool(report.final_joint_error <= FINAL_ERROR_TOLERANCE_RAD and result["stop_ok"])
        if not result["ok"]:
            result["reason"] = (f"final joint error {report.final_joint_error:.4f} rad > {FINAL_ERROR_TOLERANCE_RAD}"
                                if report.final_joint_error > FINAL_ERROR_TOLERANCE_RAD else "stop() did not interrupt")
    finally:
        backend.disconnect()
    result["total_s"] = round(time.monotonic() - started, 3)
    return result


def check_franky() -> dict:
    _require(("franky", "franky-control"), ("franky_sim", "franky-sim"))
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    from services.robot_bridge.adapters.franka import FrankaBackend

    with MujocoSimulator(enable_visualization=False) as sim:
        robot = sim.add_robot()
        with SimulationServer(sim) as server:
            server.run_async()
            backend = FrankaBackend(robot.hostname, realtime=False, relative_dynamics_factor=0.5)
            result = exercise(backend, DEVICE_LIMITS["fr3"], delta_rad=0.15, duration_s=1.0)
    return {**result, "transport": f"libfranka protocol to franky-sim at {robot.hostname}"}


def check_xarm() -> dict:
    _require(("xarm", "xarm-python-sdk"))
    from services.robot_bridge.adapters.xarm import XArmBackend
    from services.robot_bridge.devsim.xarm import FakeXArmController, fake_xarm_api

    controller = FakeXArmController()
    backend = XArmBackend("192.168.1.201", api_factory=lambda ip: fake_xarm_api(controller, ip))
    result = exercise(backend, DEVICE_LIMITS["xarm7"])
    servo_commands = sum(1 for c in controller.commands if c[0] == "move_servoj")
    return {**result, "servo_commands_received": servo_commands, "transport": "XArmAPI with a fake UxbusCmd"}


def check_leap() -> dict:
    _require(("dynamixel_sdk", "dynamixel-sdk"))
    from services.robot_bridge.adapters.leap import LeapBackend
    from services.robot_bridge.devsim.dynamixel import DynamixelBus

    with DynamixelBus(motor_ids=range(16)) as bus:
        backend = LeapBackend(bus.port_name, baudrate=4_000_000)
        result = exercise(backend, DEVICE_LIMITS["leap"])
        crc_errors = bus.crc_errors
        port = bus.port_name
    return {**result, "crc_errors": crc_errors, "transport": f"Protocol 2.0 on pty {port}"}


def check_allegro() -> dict:
    _require(("can", "python-can"))
    from services.robot_bridge.adapters.allegro import AllegroBackend
    from services.robot_bridge.devsim.allegro import SimAllegroHand

    channel = f"gd2p-selftest-{uuid.uuid4().hex[:8]}"
    with SimAllegroHand(interface="virtual", channel=channel, initial_rad=np.full(16, 0.3)):
        # The stand-in is a Python thread: on a loaded host its reports can pause longer than a real hand's.
        backend = AllegroBackend(interface="virtual", channel=channel, report_period_ms=5, stale_after_s=1.0)
        result = exercise(backend, DEVICE_LIMITS["allegro"])
    return {**result, "transport": f"python-can virtual bus {channel!r}"}


CHECKS: dict[str, Callable[[], dict]] = {
    "franky": check_franky, "xarm": check_xarm, "leap": check_leap, "allegro": check_allegro,
}


def run_selftest(devices: tuple[str, ...] = DEVICES) -> dict[str, dict]:
    """Run the chosen device checks; every device gets an entry with "ok"."""
    unknown = [d for d in devices if d not in CHECKS]
    if unknown:
        raise ValueError(f"unknown devices {unknown}; choose from {list(CHECKS)}")
    results: dict[str, dict] = {}
    for device in devices:
        try:
            results[device] = CHECKS[device]()
        except MissingPackage as exc:
            results[device] = {"ok": False, "reason": str(exc)}
        except (BackendError, OSError, ValueError) as exc:
            results[device] = {"ok": False, "reason": f"{type(exc).__name__}: {exc}"}
    return results
