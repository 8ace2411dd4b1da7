"""Hardware robots' self-test without hardware: each robot against its protocol fake.

    panda    FR3 robot -> franky-control -> libfranka protocol -> franky-sim (MuJoCo) on 127.0.0.1
    xarm7    xArm7 robot -> xarm-python-sdk -> fake controller at the SDK's transport boundary
    leap     LEAP robot -> dynamixel-sdk -> pty -> Protocol 2.0 responder (16 X-series motors)
    allegro  Allegro robot -> python-can virtual bus -> simulated Allegro V5 hand

Devices are named as everywhere else (robots/__init__.py). For each: connect, keep the trajectory
inside the device's limits, send a short trajectory and report the final joint error, then interrupt
a second trajectory with stop() (MotionStopped expected) and recover(). `run_selftest()` returns
{"panda": {"ok": bool, ...}, "xarm7": ..., "leap": ..., "allegro": ...}; a missing optional package
gives ok=false with the reason and the install command.
"""
from __future__ import annotations

import importlib.util
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

import numpy as np

from shared.execution.robot import JointTrajectory, MotionStopped, Robot, RobotError
from shared.execution.robots import DEVICES as DEVICE_NAMES

DEVICES: tuple[str, ...] = tuple(DEVICE_NAMES)  # panda, xarm7, leap, allegro
# The error a stand-in's first-order joints must settle within for ok=true (rad).
FINAL_ERROR_TOLERANCE_RAD = 0.02


class MissingPackage(RuntimeError):
    pass


def _require(*modules_and_packages: tuple[str, str]) -> None:
    missing = [package for module, package in modules_and_packages if importlib.util.find_spec(module) is None]
    if missing:
        raise MissingPackage(f"{', '.join(missing)} not installed (pip install {' '.join(missing)})")


def _trajectory(robot: Robot, delta_rad: float, duration_s: float, steps: int = 6) -> JointTrajectory:
    """From where the device is, a straight joint-space move of +-delta on every joint, kept inside its limits."""
    limits = robot.limits
    start = robot.observe().positions
    middle = (limits.lower + limits.upper) / 2
    direction = np.where(start < middle, 1.0, -1.0)  # move towards the middle of each range
    goal = np.clip(start + direction * delta_rad, limits.lower, limits.upper)
    alphas = np.linspace(0.0, 1.0, steps)
    trajectory = JointTrajectory(robot.joint_names, start + np.outer(alphas, goal - start), alphas * duration_s)
    speed = np.abs(trajectory.velocities()).max(axis=0)
    if (speed > limits.velocity).any():
        raise ValueError(f"self-test trajectory too fast for {limits.device}: {speed} rad/s")
    return trajectory


def exercise(robot: Robot, delta_rad: float = 0.2, duration_s: float = 0.6) -> dict[str, Any]:
    """connect -> send (final error) -> interrupted send (stop) -> recover -> disconnect."""
    started = time.monotonic()
    robot.connect()
    try:
        report = robot.send(_trajectory(robot, delta_rad, duration_s))
        result: dict[str, Any] = {
            "final_joint_error_rad": round(report.final_joint_error, 5),
            "execute_s": round(report.duration_s, 3),
            "commands_streamed": report.samples,
        }
        stop = threading.Event()
        timer = threading.Timer(duration_s / 3, stop.set)
        timer.start()
        try:
            robot.send(_trajectory(robot, delta_rad, duration_s), stop)
            result["stop_ok"] = False
        except MotionStopped:
            result["stop_ok"] = True
        finally:
            timer.cancel()
        robot.recover()
        state = robot.observe()
        result["state_after_recover"] = [round(float(v), 4) for v in state.positions]
        result["ok"] = bool(report.final_joint_error <= FINAL_ERROR_TOLERANCE_RAD and result["stop_ok"])
        if not result["ok"]:
            result["reason"] = (f"final joint error {report.final_joint_error:.4f} rad > {FINAL_ERROR_TOLERANCE_RAD}"
                                if report.final_joint_error > FINAL_ERROR_TOLERANCE_RAD else "stop() did not interrupt")
    finally:
        robot.disconnect()
    result["total_s"] = round(time.monotonic() - started, 3)
    return result


def check_panda() -> dict[str, Any]:
    _require(("franky", "franky-control"), ("franky_sim", "franky-sim"))
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    from shared.execution.robots.panda.config import PandaConfig
    from shared.execution.robots.panda.robot import PandaRobot

    with MujocoSimulator(enable_visualization=False) as sim:
        robot = sim.add_robot()
        with SimulationServer(sim) as server:
            server.run_async()
            panda = PandaRobot(PandaConfig(robot.hostname, realtime=False, relative_dynamics_factor=0.5))
            result = exercise(panda, delta_rad=0.15, duration_s=1.0)
    return {**result, "transport": f"libfranka protocol to franky-sim at {robot.hostname}"}


def check_xarm7() -> dict[str, Any]:
    _require(("xarm", "xarm-python-sdk"))
    from shared.execution.robots.xarm7.config import XArm7Config
    from shared.execution.robots.xarm7.fake import FakeXArmController, fake_xarm_api
    from shared.execution.robots.xarm7.robot import XArm7Robot

    controller = FakeXArmController()
    robot = XArm7Robot(XArm7Config("192.168.1.201"), api_factory=lambda ip: fake_xarm_api(controller, ip))
    result = exercise(robot)
    servo_commands = sum(1 for c in controller.commands if c[0] == "move_servoj")
    return {**result, "servo_commands_received": servo_commands, "transport": "XArmAPI with a fake UxbusCmd"}


def check_leap() -> dict[str, Any]:
    _require(("dynamixel_sdk", "dynamixel-sdk"))
    from shared.execution.robots.leap.config import LeapConfig
    from shared.execution.robots.leap.fake import DynamixelBus
    from shared.execution.robots.leap.robot import LeapRobot

    with DynamixelBus(motor_ids=range(16)) as bus:
        result = exercise(LeapRobot(LeapConfig(bus.port_name, baudrate=4_000_000)))
        crc_errors = bus.crc_errors
        port = bus.port_name
    return {**result, "crc_errors": crc_errors, "transport": f"Protocol 2.0 on pty {port}"}


def check_allegro() -> dict[str, Any]:
    _require(("can", "python-can"))
    from shared.execution.robots.allegro.config import AllegroConfig
    from shared.execution.robots.allegro.fake import SimAllegroHand
    from shared.execution.robots.allegro.robot import AllegroRobot

    channel = f"gd2p-selftest-{uuid.uuid4().hex[:8]}"
    with SimAllegroHand(interface="virtual", channel=channel, initial_rad=np.full(16, 0.3)):
        # The stand-in is a Python thread: on a loaded host its reports can pause longer than a real hand's.
        result = exercise(AllegroRobot(AllegroConfig(interface="virtual", channel=channel, report_period_ms=5,
                                                     stale_after_s=1.0)))
    return {**result, "transport": f"python-can virtual bus {channel!r}"}


CHECKS: dict[str, Callable[[], dict[str, Any]]] = {
    "panda": check_panda, "xarm7": check_xarm7, "leap": check_leap, "allegro": check_allegro,
}


def run_selftest(devices: tuple[str, ...] = DEVICES) -> dict[str, dict[str, Any]]:
    """Run the chosen device checks; every device gets an entry with "ok"."""
    unknown = [d for d in devices if d not in CHECKS]
    if unknown:
        raise ValueError(f"unknown devices {unknown}; choose from {list(CHECKS)}")
    results: dict[str, dict[str, Any]] = {}
    for device in devices:
        try:
            results[device] = CHECKS[device]()
        except MissingPackage as exc:
            results[device] = {"ok": False, "reason": str(exc)}
        except (RobotError, OSError, ValueError) as exc:
            results[device] = {"ok": False, "reason": f"{type(exc).__name__}: {exc}"}
    return results
