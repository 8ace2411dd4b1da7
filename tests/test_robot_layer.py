"""The robot layer: one Robot contract, one safety executor for every robot, limits from the URDFs, one vocabulary.

The executor runs here on two in-memory devices (an xArm7 and a LEAP hand that follow every command at
once), with a lease and an e-stop given as plain Python objects: no bus, no hardware.
"""
from __future__ import annotations

import ast
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from shared.contracts.messages import ARMS, HANDS, EStop, ExecutionCommand, Plan
from shared.execution.executor import EStopLatch, Executor, LocalLease
from shared.execution.limits import DeviceLimits
from shared.execution.robot import Observation, StreamingRobot
from shared.execution.robots import DEVICES
from shared.execution.robots.allegro import config as allegro_config
from shared.execution.robots.leap import config as leap_config
from shared.execution.robots.panda import config as panda_config
from shared.execution.robots.xarm7 import config as xarm7_config
from shared.robots.robot_limits import JointLimits

ROOT = Path(__file__).resolve().parents[1]
XARM_HOME = np.array([0.0, -0.4, 0.0, 0.9, 0.0, 1.3, 0.0])


class MemoryDevice(StreamingRobot):
    """A device that is wherever it was last commanded (counts the commands it was sent)."""

    def __init__(self, name: str, limits: DeviceLimits, start: np.ndarray):
        self.name = name
        super().__init__(limits.joint_names, limits, command_rate_hz=200.0)
        self.positions = np.asarray(start, dtype=np.float64).copy()
        self.commands = 0
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    def observe(self) -> Observation:
        return Observation(time.time(), self.joint_names, self.positions.copy(), np.zeros(len(self.joint_names)))

    def _send_positions(self, q: np.ndarray) -> None:
        self.commands += 1
        self.positions = np.asarray(q, dtype=np.float64).copy()


class EngagedEStop:
    """An e-stop someone has pressed (the EmergencyStop interface, nothing else)."""

    engaged = True
    reason = "pressed on the pendant"

    def engage(self, msg: EStop) -> None:
        raise AssertionError("already engaged")

    def guard(self, robots) -> None:
        self.robots = list(robots)


def devices() -> tuple[MemoryDevice, MemoryDevice]:
    arm = MemoryDevice("xarm7", xarm7_config.limits(), XARM_HOME)
    hand = MemoryDevice("leap", leap_config.limits(), np.zeros(16))
    arm.connect()
    hand.connect()
    return arm, hand


def command(arm_goal: np.ndarray, duration_s: float, steps: int = 10) -> ExecutionCommand:
    start = np.concatenate([XARM_HOME, np.zeros(16)])
    goal = np.concatenate([arm_goal, np.zeros(16)])
    alphas = np.linspace(0.0, 1.0, steps)[:, None]
    plan = Plan(arm="xarm7", hand="leap", joint_names=[*xarm7_config.limits().joint_names, *leap_config.limits().joint_names],
                positions=start + alphas * (goal - start), times_s=np.linspace(0.0, duration_s, steps))
    return ExecutionCommand(plan=plan, lease_token="in-process")


def test_a_plan_runs_on_every_device_to_its_end():
    arm, hand = devices()
    executor = Executor("xarm7", "leap", [arm, hand], EStopLatch())
    state = executor.execute(command(XARM_HOME + 0.2, 0.3), LocalLease())
    assert state.status == "done", state.message
    np.testing.assert_allclose(arm.positions, XARM_HOME + 0.2)
    assert state.joint_names[:7] == list(arm.joint_names) and len(state.joint_names) == 23


def test_a_lease_lost_mid_motion_stops_every_device_and_names_the_loss():
    arm, hand = devices()
    executor = Executor("xarm7", "leap", [arm, hand], EStopLatch())
    lease = LocalLease()
    threading.Timer(0.3, lease.release, args=("the commander left",)).start()
    goal = XARM_HOME + 0.5
    state = executor.execute(command(goal, 2.0), lease)
    assert state.status == "stopped", state.message
    assert state.message.startswith("the commander left; motion halted") and "s after the loss was noticed" in state.message
    assert np.max(np.abs(arm.positions - goal)) > 0.2  # it did not get there
    assert not arm._stop_requested.is_set() and not hand._stop_requested.is_set()  # recovered: a lost lease is no fault
    again = executor.execute(command(arm.positions, 0.2), LocalLease())
    assert again.status == "refused" and again.message.startswith("start:")  # ready again; this plan starts elsewhere


def test_a_lease_lost_before_motion_refuses_and_nothing_moves():
    arm, hand = devices()
    lease = LocalLease()
    lease.release("cancelled")
    state = Executor("xarm7", "leap", [arm, hand], EStopLatch()).execute(command(XARM_HOME + 0.2, 0.3), lease)
    assert state.status == "refused" and state.message.startswith("lease:") and "cancelled" in state.message
    assert arm.commands == hand.commands == 0


def test_an_engaged_estop_refuses_commands_before_anything_moves():
    arm, hand = devices()
    estop = EngagedEStop()
    executor = Executor("xarm7", "leap", [arm, hand], estop)
    assert estop.robots == [arm, hand]  # the executor put its robots under the e-stop
    state = executor.execute(command(XARM_HOME + 0.2, 0.3), LocalLease())
    assert state.status == "refused" and "e-stop is latched (pressed on the pendant)" in state.message
    assert arm.commands == hand.commands == 0


def test_an_estop_that_lands_before_a_device_starts_is_reported_as_the_estop():
    """On a busy machine the e-stop can stop a device between the executor's checks and its first command: the
    device then refuses to start, and the report names the operator's stop, not a device fault."""
    arm, hand = devices()
    latch = EStopLatch()
    executor = Executor("xarm7", "leap", [arm, hand], latch)
    send = arm.send

    def send_after_the_estop(*args, **kwargs):
        latch.engage(EStop(reason="person in the cell"))
        arm._stop_requested.wait(1.0)  # the latch's thread has stopped the device
        return send(*args, **kwargs)

    arm.send = send_after_the_estop  # type: ignore[method-assign]
    state = executor.execute(command(XARM_HOME + 0.5, 2.0), LocalLease())
    assert state.status == "stopped" and state.message.startswith("e-stop: person in the cell"), state.message


def test_the_estop_latch_stops_a_running_motion_and_stays_latched():
    arm, hand = devices()
    latch = EStopLatch()
    executor = Executor("xarm7", "leap", [arm, hand], latch)
    threading.Timer(0.3, latch.engage, args=(EStop(reason="person in the cell"),)).start()
    state = executor.execute(command(XARM_HOME + 0.5, 2.0), LocalLease())
    assert state.status == "stopped" and state.message.startswith("e-stop: person in the cell"), state.message
    assert executor.execute(command(arm.positions, 0.2), LocalLease()).status == "refused"
    latch.reset()
    assert not latch.engaged and not arm._stop_requested.is_set()


def test_the_simulated_robot_and_the_hardware_robots_share_one_executor():
    """The evaluation's simulated robot and the hardware robots built from flags run behind the same Executor."""
    import argparse

    from evaluation.local_system import LocalRobot
    from shared.execution.hardware import HardwareSpec
    from shared.execution.robots.sim.robot import SimRobot

    local = LocalRobot()
    try:
        simulated = local.executor("panda", "allegro")
        assert isinstance(simulated.robots[0], SimRobot)
    finally:
        local.close()
    parser = argparse.ArgumentParser()
    HardwareSpec.add_cli_args(parser)
    spec = HardwareSpec.from_args(parser.parse_args(["--hardware", "xarm7+leap", "--xarm7-ip", "10.0.0.2",
                                                     "--leap-port", "/dev/ttyUSB0"]))
    hardware = Executor(spec.arm, spec.hand, spec.robots(), EStopLatch())  # robots built, not connected
    assert type(simulated) is type(hardware) is Executor
    assert [r.name for r in hardware.robots] == ["xarm7", "leap"]


def test_device_limits_are_the_urdfs_except_what_the_real_device_differs_on():
    xarm7, leap, allegro, panda = (c.limits() for c in (xarm7_config, leap_config, allegro_config, panda_config))
    for limits, urdf in ((xarm7, JointLimits.of_arm("xarm7")), (panda, JointLimits.of_arm("panda")),
                         (leap, JointLimits.of_hand("leap")), (allegro, JointLimits.of_hand("allegro"))):
        assert limits.joint_names == urdf.joint_names
        if limits.device != "panda":  # positions and speeds from the URDF
            for kind in ("lower", "upper", "velocity"):
                np.testing.assert_array_equal(getattr(limits, kind), getattr(urdf, kind))
    np.testing.assert_array_equal(xarm7.effort, JointLimits.of_arm("xarm7").effort)  # Nm, as the SDK reports
    np.testing.assert_array_equal(panda.effort, JointLimits.of_arm("panda").effort)
    assert panda.upper[3] == pytest.approx(-0.1169) and panda.velocity[4] == pytest.approx(5.26)  # FR3, not Panda
    assert (leap.effort_unit, leap.effort[0]) == ("mA", 550.0) and (allegro.effort_unit, allegro.effort[0]) == ("mA", 240.0)


def test_one_vocabulary_for_arms_and_hands():
    from cli.main import build_parser
    from shared.execution.selftest import CHECKS

    assert set(DEVICES) == set(ARMS) | set(HANDS) == set(CHECKS)
    assert {d.kind for d in DEVICES.values()} == {"arm", "hand"}
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bridge", "selftest", "--device", "franky"])
    assert build_parser().parse_args(["bridge", "selftest", "--device", "panda"]).device == ["panda"]


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_only_the_bus_adapter_of_the_robot_bridge_imports_zenoh():
    bridge = ROOT / "services" / "robot_bridge"
    importers = {p.relative_to(bridge).as_posix() for p in bridge.rglob("*.py")
                 if any(name == "zenoh" or name.startswith("zenoh.") for name in _imports(p))}
    assert importers == {"service.py", "bus_safety.py"}
    code = ("import sys, shared.execution.executor, shared.execution.hardware, "
            "shared.execution.selftest, shared.execution.robots.sim.robot; "
            "sys.exit('zenoh' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT, timeout=120).returncode == 0


def test_services_never_import_each_other():
    services = [p for p in (ROOT / "services").iterdir() if p.is_dir() and (p / "__init__.py").exists()]
    assert {"planner", "robot_bridge", "validator"} <= {p.name for p in services}
    for service in services:
        for path in service.rglob("*.py"):
            others = {name.split(".")[1] for name in _imports(path)
                      if name.startswith("services.") and name.split(".")[1] != service.name}
            assert not others, f"{path.relative_to(ROOT)} imports services {sorted(others)}"


def test_hardware_states_carry_a_users_tracker_pose_and_the_plan_time(zenoh_router):
    """On hardware the object's pose comes from the user's tracker on the object-track key: the bridge folds
    its latest pose into the states it publishes while a plan runs (where the closed-loop monitor reads it)."""
    from services.robot_bridge.service import TRACK_FRESH_S, TRACK_KEY, TrackSubscriber
    from shared.bus import BusConfig, open_session
    from shared.contracts.codec import encode
    from shared.contracts.messages import ObjectPose, ObjectTrack

    cfg = BusConfig(mode="client", connect=[zenoh_router], connect_timeout_ms=5000)
    seen = ObjectPose(position=(0.42, 0.05, 0.03))
    with open_session(cfg) as bridge_session, open_session(cfg) as tracker_session:
        tracks = TrackSubscriber(bridge_session)
        quiet = threading.Event()

        def track() -> None:  # the user's tracker, at 20 Hz
            while not quiet.is_set():
                payload, encoding = encode(ObjectTrack(stamp=time.time(), pose=seen, source="apriltag-cam"))
                tracker_session.put(TRACK_KEY, payload, encoding=encoding)
                time.sleep(0.05)

        threading.Thread(target=track, daemon=True).start()
        deadline = time.monotonic() + 5.0
        while tracks.latest() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        states = []
        arm, hand = devices()
        executor = Executor("xarm7", "leap", [arm, hand], EStopLatch(), publish=states.append,
                            tracked_object=tracks.latest)
        assert executor.execute(command(XARM_HOME + 0.1, 0.4), LocalLease()).status == "done"
        quiet.set()
        tracks.close()
    executing = [s for s in states if s.status == "executing"]
    assert executing and all(s.object_pose == seen for s in executing)
    assert np.all(np.diff([s.plan_time_s for s in executing]) > 0)
    time.sleep(TRACK_FRESH_S + 0.1)
    assert tracks.latest() is None  # a tracker gone quiet is not believed


def test_a_halted_motion_waits_a_moment_for_the_estop_message_to_say_why():
    """The bus adapter stops the robots before it decodes the e-stop message; a report of the halted motion made
    in between (a busy machine) waits for the message rather than saying "a message on the e-stop key"."""
    latch = EStopLatch()
    latch.stop_now()
    threading.Timer(0.05, latch.describe, args=(EStop(reason="person in the cell"),)).start()
    assert latch.reason == "a message on the e-stop key"
    assert latch.reason_once_described() == "person in the cell"
    latch.reset()
    assert latch.reason_once_described(wait_s=0.01) == "a message on the e-stop key"  # nothing to wait for: no hang
