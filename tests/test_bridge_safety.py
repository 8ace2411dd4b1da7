"""Safety of the hardware bridge: limits before motion, the commander's lease, the e-stop.

The robot is an xArm7 (xarm-python-sdk with a fake controller at its transport boundary) carrying a
LEAP hand (dynamixel-sdk talking Protocol 2.0 to a responder on a pty), driven by the safety `Executor`
with its commands leased on a real Zenoh session through an in-process router (`LeasedExecutor`).
"""
from __future__ import annotations

import json
import os
import threading
import time

import numpy as np
import pytest

pytest.importorskip("xarm")
pytest.importorskip("dynamixel_sdk")

import zenoh

from services.robot_bridge import bus_safety as safety
from services.robot_bridge.bus_safety import ESTOP_KEY, EStopSubscriber, LeasedExecutor, check_command_lease
from shared.bus.keys import alive_key
from shared.bus.lease import RouterWatchdog, lease_alive, lease_key, lease_present
from shared.contracts.codec import encode
from shared.contracts.messages import ErrorReply, EStop, ExecutionCommand, Plan
from shared.execution.executor import EStopLatch, Executor
from shared.execution.limits import SafetyRefusal
from shared.execution.robot import MotionStopped
from shared.execution.robots.leap import config as leap_config
from shared.execution.robots.leap import fake as dx
from shared.execution.robots.leap.config import LeapConfig
from shared.execution.robots.leap.fake import DynamixelBus
from shared.execution.robots.leap.robot import LeapRobot
from shared.execution.robots.xarm7 import config as xarm7_config
from shared.execution.robots.xarm7.config import XArm7Config
from shared.execution.robots.xarm7.fake import FakeXArmController, fake_xarm_api
from shared.execution.robots.xarm7.robot import XArm7Robot

XARM_HOME = np.array([0.0, -0.4, 0.0, 0.9, 0.0, 1.3, 0.0])
HAND_OPEN = np.zeros(16)
LEASE = lease_key("planner", "planner-test.1")
XARM7_LIMITS, LEAP_LIMITS = xarm7_config.limits(), leap_config.limits()
STOP_BOUND_S = 0.5  # the target is 0.2 s; slack for a loaded 2-core CI machine


def client(endpoint: str) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("client"))
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


class Robot:
    """xArm7 + LEAP hand stand-ins, connected, behind the safety executor with leased commands and the e-stop key."""

    def __init__(self, endpoint: str, current_limit_ma: float = 550.0, watchdog: bool = False):
        self.session = client(endpoint)
        self.probe = client(endpoint) if watchdog else None  # the router watchdog's second session
        self.watchdog = RouterWatchdog(self.session, self.probe, "bridge-test") if watchdog else None
        self.controller = FakeXArmController(initial_rad=XARM_HOME)
        self.bus = DynamixelBus(motor_ids=range(16))
        self.arm = XArm7Robot(XArm7Config("192.168.1.201"), api_factory=lambda ip: fake_xarm_api(self.controller, ip))
        self.hand = LeapRobot(LeapConfig(self.bus.port_name, current_limit_ma=current_limit_ma))
        self.arm.connect()
        self.hand.connect()
        self.published: list = []  # ExecutionStates published while executing
        self.estop = EStopSubscriber(self.session, EStopLatch())
        self.executor = LeasedExecutor(self.session, Executor("xarm7", "leap", [self.arm, self.hand], self.estop.latch,
                                                              publish=self.published.append), watchdog=self.watchdog)
        self._connected_at = (len(self.controller.commands), len(self.bus.instructions))
        self.stopped_at: dict[str, float] = {}  # device -> time.monotonic() its execute() ended in MotionStopped
        for backend in (self.arm, self.hand):
            backend.send = self._timed(backend.name, backend.send)

    def _timed(self, name: str, send):
        def timed(*args, **kwargs):
            try:
                return send(*args, **kwargs)
            except MotionStopped:
                self.stopped_at.setdefault(name, time.monotonic())
                raise
        return timed

    def halt_latency(self, fault_at: float) -> float:
        """From the fault to the moment the last device had halted."""
        assert set(self.stopped_at) == {self.arm.name, self.hand.name}, self.stopped_at
        return max(self.stopped_at.values()) - fault_at

    def moved(self) -> bool:
        """Any motion command reached either device since connect."""
        servo = any(c[0] == "move_servoj" for c in self.controller.commands[self._connected_at[0]:])
        sync_writes = any(i == dx.INST_SYNC_WRITE for i, _ in self.bus.instructions[self._connected_at[1]:])
        return servo or sync_writes

    def close(self) -> None:
        self.estop.close()
        if self.watchdog is not None:
            self.watchdog.close()
            self.probe.close()
        self.arm.disconnect()
        self.hand.disconnect()
        self.bus.close()
        self.session.close()


@pytest.fixture()
def robot(zenoh_router):
    r = Robot(zenoh_router)
    yield r
    r.close()


@pytest.fixture()
def planner(zenoh_router):
    """The commander's session holding its lease (liveliness token)."""
    session = client(zenoh_router)
    token = session.liveliness().declare_token(LEASE)
    yield session, token
    session.close()


def plan(arm_goal=XARM_HOME, hand_goal=HAND_OPEN, duration_s=0.6, steps=4, arm_start=XARM_HOME,
         hand_start=HAND_OPEN) -> Plan:
    alphas = np.linspace(0.0, 1.0, steps)[:, None]
    start = np.concatenate([arm_start, hand_start])
    goal = np.concatenate([np.asarray(arm_goal, dtype=float), np.asarray(hand_goal, dtype=float)])
    return Plan(arm="xarm7", hand="leap", joint_names=[*XARM7_LIMITS.joint_names, *LEAP_LIMITS.joint_names],
                positions=start + alphas * (goal - start), times_s=np.linspace(0.0, duration_s, steps))


def command(p: Plan, lease: str = LEASE, realtime_factor: float = 1.0) -> ExecutionCommand:
    return ExecutionCommand(plan=p, lease_token=lease, realtime_factor=realtime_factor)


def wait_for_lease(session: zenoh.Session, present: bool = True, timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while lease_alive(session, LEASE, 0.2) != present:
        assert time.monotonic() < deadline, f"lease presence never became {present}"
        time.sleep(0.05)


# ------------------------------------------------------------------------------------------ limits
def test_a_valid_plan_with_a_live_lease_moves_both_devices(robot, planner):
    wait_for_lease(robot.session)
    goal_arm, goal_hand = XARM_HOME + 0.1, np.full(16, 0.3)
    state = robot.executor.execute(command(plan(goal_arm, goal_hand)))
    assert state.status == "done", state.message
    np.testing.assert_allclose(robot.controller.positions, goal_arm, atol=0.01)
    np.testing.assert_allclose(np.array(robot.bus.positions_rad()) - np.pi, goal_hand, atol=0.02)
    assert state.joint_names[:7] == list(XARM7_LIMITS.joint_names)
    executing = [s for s in robot.published if s.command_id == state.command_id]
    assert len(executing) >= 15 and {s.status for s in executing} == {"executing"}  # ~50 Hz for >= 0.6 s
    assert len(executing[0].joint_names) == 23 and np.all(np.diff([s.stamp for s in executing]) > 0)


@pytest.mark.parametrize("case, check", [
    ("hand joint beyond its limit", "joint position"),
    ("arm joint too fast", "joint velocity"),
    ("fine at 1x, too fast at 20x", "joint velocity"),
    ("flange under the table", "workspace box"),
    ("plan starts elsewhere", "start"),
])
def test_a_plan_outside_the_limits_is_refused_before_anything_moves(robot, planner, case, check):
    wait_for_lease(robot.session)
    factor = 1.0
    if case == "hand joint beyond its limit":
        hand = np.zeros(16)
        hand[1] = 2.5  # LEAP joint 1 ends at 2.23 rad
        p = plan(hand_goal=hand, duration_s=2.0)
    elif case == "arm joint too fast":
        p = plan(arm_goal=XARM_HOME + np.array([0.6, 0, 0, 0, 0, 0, 0]), duration_s=0.1, steps=2)  # 6 rad/s
    elif case == "fine at 1x, too fast at 20x":
        p = plan(arm_goal=XARM_HOME + np.array([0.6, 0, 0, 0, 0, 0, 0]), duration_s=2.0)
        factor = 20.0
    elif case == "flange under the table":
        bent = XARM_HOME.copy()
        bent[1] = 1.2  # leaning forward with the elbow bent: flange ~0.1 m below the table top
        p = plan(arm_goal=bent, duration_s=4.0, steps=8)
    else:
        p = plan(arm_start=XARM_HOME + 0.3, arm_goal=XARM_HOME + 0.3, duration_s=1.0)
    state = robot.executor.execute(command(p, realtime_factor=factor))
    assert state.status == "refused"
    assert check in state.message
    assert not robot.moved()


def test_an_effort_cap_above_the_device_limit_is_refused(zenoh_router, planner):
    robot = Robot(zenoh_router, current_limit_ma=900.0)  # LEAP limit: 550 mA
    try:
        state = robot.executor.execute(command(plan(hand_goal=np.full(16, 0.1))))
        assert state.status == "refused" and "900 mA, above its limit 550 mA" in state.message
        assert not robot.moved()
    finally:
        robot.close()


def test_a_measured_effort_over_its_limit_stops_every_device_and_latches(robot, planner):
    wait_for_lease(robot.session)
    def contact() -> None:  # 0.4 s in, the arm runs into something: joint 2 loads up to 65 Nm (limit 50)
        robot.controller.external_torques[1] = 65.0

    threading.Timer(0.4, contact).start()
    goal = XARM_HOME + 0.6
    state = robot.executor.execute(command(plan(goal, np.full(16, 0.8), duration_s=2.0, steps=6)))
    assert state.status == "stopped" and "effort" in state.message and "Nm" in state.message
    assert np.max(np.abs(robot.controller.positions - goal)) > 0.2
    assert np.max(np.abs(np.array(robot.bus.positions_rad()) - np.pi - 0.8)) > 0.2  # the hand stopped too
    here = np.concatenate([robot.arm.observe().positions, robot.hand.observe().positions])
    refused = robot.executor.execute(command(plan(here[:7], here[7:], arm_start=here[:7], hand_start=here[7:])))
    assert refused.status == "refused" and "protective stop" in refused.message  # latched until an operator resets


# ------------------------------------------------------------------------------------------ lease
def test_a_command_lease_must_be_a_planner_lease_key():
    for bad in ("gd2p/lease/planner/*", "gd2p/lease/**", "", "gd2p/lease/planner//x", "gd2p/lease/planner/$*a",
                "gd2p/lease/planner-test", "gd2p/lease/planner/a/b/c", "gd2p/lease/planner/x-1", "gd2p/lease/client/c-1",
                "gd2p/lease/client/cli/c-1", "gd2p/lease/planner/*/x", "gd2p/alive/recorder/r1"):
        with pytest.raises(SafetyRefusal, match="lease"):
            check_command_lease(bad)
    assert check_command_lease(LEASE) == LEASE == "gd2p/lease/planner/planner/planner-test.1"


@pytest.mark.parametrize("key", ["gd2p/lease/client/cli/c-1", alive_key("recorder", "rec-1"), "gd2p/lease/planner-test"])
def test_a_live_token_that_is_not_a_planner_lease_commands_nothing(robot, zenoh_router, key):
    other = client(zenoh_router)  # e.g. the recorder's session, or a client's lease: alive, but no planner lease
    try:
        token = other.liveliness().declare_token(key)
        deadline = time.monotonic() + 5.0  # the token is there (a single query may come back empty) ...
        while not lease_present(robot.session, key, 1.0):
            assert time.monotonic() < deadline, f"the token on {key} never showed up"
        state = robot.executor.execute(command(plan(XARM_HOME + 0.1), lease=key))  # ... and commands nothing
        token.undeclare()
    finally:
        other.close()
    assert state.status == "refused" and state.message.startswith("lease:"), state.message
    assert "gd2p/lease/planner/<identity>/<holder>" in state.message
    assert not robot.moved()


def test_a_command_whose_lease_is_not_alive_is_refused(robot):
    state = robot.executor.execute(command(plan(XARM_HOME + 0.1)))
    assert state.status == "refused" and "lease" in state.message and "not alive" in state.message
    assert not robot.moved()


def test_a_command_arriving_after_the_lease_is_lost_is_refused(robot, planner):
    session, token = planner
    wait_for_lease(robot.session)
    token.undeclare()  # the planner lost its lease (crashed, network gone, session closed)
    wait_for_lease(robot.session, present=False)
    state = robot.executor.execute(command(plan(XARM_HOME + 0.1)))
    assert state.status == "refused" and "not alive" in state.message
    assert not robot.moved()


def test_losing_the_lease_mid_execution_stops_the_motion(robot, zenoh_router):
    commander = client(zenoh_router)
    token = commander.liveliness().declare_token(LEASE)
    fault_at: list[float] = []

    def leave() -> None:  # the commander's process goes away
        fault_at.append(time.monotonic())
        commander.close()

    try:
        wait_for_lease(robot.session)
        goal = XARM_HOME + 0.8
        threading.Timer(0.5, leave).start()
        state = robot.executor.execute(command(plan(goal, duration_s=3.0, steps=10)))
        latency = robot.halt_latency(fault_at[0])
        print(f"commander left -> xArm + LEAP halted: {latency * 1000:.0f} ms")
        assert state.status == "stopped" and f"lease {LEASE!r} lost" in state.message, state.message
        assert "s after the loss was noticed" in state.message
        assert latency <= STOP_BOUND_S
        assert np.max(np.abs(robot.controller.positions - goal)) > 0.3  # it did not get there
        assert ("set_state", 4) in robot.controller.commands  # the controller was told to stop
        assert robot.controller.state == 0  # and made ready again: a lost lease is no fault
    finally:
        del token
        if not commander.is_closed():
            commander.close()


def test_the_motion_stops_when_the_executor_loses_its_router():
    from conftest import free_port, router_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(router_config(endpoint))
    robot = Robot(endpoint)
    commander = client(endpoint)
    fault_at: list[float] = []

    def router_dies() -> None:
        fault_at.append(time.monotonic())
        router.close()

    try:
        token = commander.liveliness().declare_token(LEASE)  # noqa: F841 - held until the router goes
        wait_for_lease(robot.session)
        goal = XARM_HOME + 0.8
        threading.Timer(0.5, router_dies).start()
        state = robot.executor.execute(command(plan(goal, duration_s=3.0, steps=10)))
        latency = robot.halt_latency(fault_at[0])
        print(f"router closed -> xArm + LEAP halted: {latency * 1000:.0f} ms")
    finally:
        robot.close()
        commander.close()
        if not router.is_closed():
            router.close()
    assert state.status == "stopped" and f"lease {LEASE!r} lost" in state.message, state.message
    assert latency <= STOP_BOUND_S
    assert np.max(np.abs(robot.controller.positions - goal)) > 0.3


def test_the_motion_stops_when_the_router_hangs():
    """A router that stops forwarding without closing its links (SIGSTOP): the executor's RouterWatchdog notices."""
    import signal
    import subprocess
    import sys

    from conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code = ("import time; from conftest import router_config; import zenoh; "
            f"s = zenoh.open(router_config({endpoint!r})); print('up', flush=True); time.sleep(120)")
    router = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.abspath(__file__)))
    robot = commander = None
    fault_at: list[float] = []

    def router_hangs() -> None:
        fault_at.append(time.monotonic())
        router.send_signal(signal.SIGSTOP)

    try:
        assert router.stdout.readline().strip() == "up"
        robot = Robot(endpoint, watchdog=True)
        commander = client(endpoint)
        token = commander.liveliness().declare_token(LEASE)  # noqa: F841 - held throughout
        wait_for_lease(robot.session)
        goal = XARM_HOME + 0.8
        threading.Timer(0.5, router_hangs).start()
        state = robot.executor.execute(command(plan(goal, duration_s=3.0, steps=10)))
        latency = robot.halt_latency(fault_at[0])
        print(f"router hung -> xArm + LEAP halted: {latency * 1000:.0f} ms")
    finally:
        router.send_signal(signal.SIGCONT)
        router.kill()
        router.wait(timeout=10)
        for thing in (robot, commander):
            if thing is not None:
                thing.close()
    assert state.status == "stopped" and "router forwarded nothing" in state.message, state.message
    assert latency <= STOP_BOUND_S
    assert np.max(np.abs(robot.controller.positions - goal)) > 0.3


# ------------------------------------------------------------------------------------------ e-stop
def test_an_estop_message_stops_every_backend_at_once_and_latches(robot, planner, zenoh_router):
    session, _ = planner
    wait_for_lease(robot.session)
    payload, encoding = encode(EStop(reason="person in the cell", issued_by="operator"))
    threading.Timer(0.4, lambda: session.put(ESTOP_KEY, payload, encoding=encoding)).start()
    arm_goal, hand_goal = XARM_HOME + 0.8, np.full(16, 1.0)
    state = robot.executor.execute(command(plan(arm_goal, hand_goal, duration_s=3.0, steps=10)))
    assert state.status == "stopped" and "person in the cell" in state.message
    assert robot.controller.state == 4  # xArm: stop state
    hand_now = np.array(robot.bus.positions_rad()) - np.pi
    assert np.max(np.abs(hand_now - hand_goal)) > 0.3  # the hand stopped short too
    time.sleep(0.2)
    np.testing.assert_allclose(np.array(robot.bus.positions_rad()) - np.pi, hand_now, atol=0.02)  # and holds

    here_arm = robot.arm.observe().positions
    here_hand = robot.hand.observe().positions
    refused = robot.executor.execute(command(plan(here_arm, here_hand, arm_start=here_arm, hand_start=here_hand)))
    assert refused.status == "refused" and "e-stop is latched" in refused.message
    robot.executor.estop.reset()
    again = robot.executor.execute(command(plan(here_arm + 0.05, here_hand, arm_start=here_arm, hand_start=here_hand)))
    assert again.status == "done", again.message


ESTOP_PAYLOADS = {
    "empty": (b"", None),
    "garbage": (b"\xff\x00garbage", "application/msgpack;EStop"),
    "wrong encoding": (b"STOP", "text/plain"),
    "ErrorReply": encode(ErrorReply(code="internal", message="not a stop")),
    "Plan": encode(plan()),
}


@pytest.mark.parametrize("kind", sorted(ESTOP_PAYLOADS))
def test_anything_on_the_estop_key_stops_every_device_mid_motion(robot, planner, kind):
    session, _ = planner
    wait_for_lease(robot.session)
    payload, encoding = ESTOP_PAYLOADS[kind]
    fault_at: list[float] = []

    def publish() -> None:
        fault_at.append(time.monotonic())
        session.put(ESTOP_KEY, payload, encoding=encoding)

    threading.Timer(0.4, publish).start()
    arm_goal = XARM_HOME + 0.8
    state = robot.executor.execute(command(plan(arm_goal, np.full(16, 1.0), duration_s=3.0, steps=10)))
    latency = robot.halt_latency(fault_at[0])
    print(f"e-stop ({kind}) -> xArm + LEAP halted: {latency * 1000:.0f} ms")
    assert state.status == "stopped" and state.message.startswith("e-stop: "), state.message
    assert latency <= STOP_BOUND_S
    assert robot.controller.state == 4  # xArm: stop state
    assert np.max(np.abs(robot.controller.positions - arm_goal)) > 0.3
    assert robot.executor.estop.triggered.is_set() and "e-stop key" in robot.executor.estop.reason


def test_the_estop_stops_before_it_decodes_and_whatever_decoding_does(robot, planner, monkeypatch):
    """The stop has started before the payload is even decoded, and a decoder that blows up changes nothing."""
    session, _ = planner
    stopped = threading.Event()
    seen_by_decode: list[bool] = []

    class Recorder:
        name, joint_names = "probe", ()

        def stop(self):
            stopped.set()

    def exploding_decode(*_args, **_kwargs):
        seen_by_decode.append(stopped.wait(1.0))  # an implementation that decodes first never gets here stopped
        raise RuntimeError("decoder crashed")

    monkeypatch.setattr(safety, "decode", exploding_decode)
    latch = EStopLatch([Recorder()])
    subscriber = EStopSubscriber(robot.session, latch)
    try:
        time.sleep(0.2)
        session.put(ESTOP_KEY, b"STOP")
        assert stopped.wait(2.0) and latch.triggered.wait(1.0)
        deadline = time.monotonic() + 2.0
        while latch.last is None and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        subscriber.close()
    assert seen_by_decode and all(seen_by_decode)  # this latch's decode, and the robot executor's own latch's
    assert "RuntimeError: decoder crashed" in latch.reason


def test_gd2p_bridge_estop_publishes_an_estop(zenoh_router):
    from cli.main import main
    from shared.contracts.codec import decode

    received: list[EStop] = []
    with client(zenoh_router) as listener:
        subscriber = listener.declare_subscriber(
            ESTOP_KEY, lambda s: received.append(decode(s.payload.to_bytes(), str(s.encoding), EStop)))
        time.sleep(0.2)
        assert main(["bridge", "estop", "--connect", zenoh_router, "--reason", "test stop"]) == 0
        deadline = time.monotonic() + 2.0
        while not received and time.monotonic() < deadline:
            time.sleep(0.05)
        subscriber.undeclare()
    assert [m.reason for m in received] == ["test stop"]


@pytest.mark.hardware_sim
@pytest.mark.skipif(os.environ.get("GD2P_HARDWARE_SIM") != "1", reason="franky-sim is opt-in: GD2P_HARDWARE_SIM=1")
def test_fr3_and_allegro_behind_the_safe_executor(zenoh_router):
    """Panda-named plans on a Franka FR3 (franky-sim) + Allegro V5 (virtual CAN): runs, and a lost lease stops the FR3."""
    pytest.importorskip("franky")
    pytest.importorskip("franky_sim")
    pytest.importorskip("can")
    import uuid

    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    from shared.execution.robots.allegro.config import AllegroConfig
    from shared.execution.robots.allegro.fake import SimAllegroHand
    from shared.execution.robots.allegro.robot import AllegroRobot
    from shared.execution.robots.panda.config import PandaConfig
    from shared.execution.robots.panda.robot import PandaRobot

    channel = f"fr3-test-{uuid.uuid4().hex[:6]}"
    with MujocoSimulator(enable_visualization=False) as sim, SimAllegroHand(channel=channel, initial_rad=np.full(16, 0.3)):
        model = sim.add_robot()
        with SimulationServer(sim) as server, client(zenoh_router) as session, client(zenoh_router) as commander:
            server.run_async()
            arm = PandaRobot(PandaConfig(model.hostname, realtime=False, relative_dynamics_factor=0.5))
            # The simulated hand is a Python thread on a loaded host: allow it longer gaps than a real hand.
            hand = AllegroRobot(AllegroConfig(interface="virtual", channel=channel, report_period_ms=10, stale_after_s=1.0))
            arm.connect()
            hand.connect()
            estop = EStopSubscriber(session, EStopLatch())
            executor = LeasedExecutor(session, Executor("panda", "allegro", [arm, hand], estop.latch))
            try:
                token = commander.liveliness().declare_token(LEASE)
                wait_for_lease(session)
                names = [*arm.joint_names, *hand.joint_names]

                def fr3_plan(delta: float, duration_s: float) -> Plan:
                    start = np.concatenate([arm.observe().positions, hand.observe().positions])
                    goal = start + np.concatenate([np.full(7, delta), np.zeros(16)])
                    alphas = np.linspace(0.0, 1.0, 5)[:, None]
                    return Plan(arm="panda", hand="allegro", joint_names=names, positions=start + alphas * (goal - start),
                                times_s=np.linspace(0.0, duration_s, 5))

                done = executor.execute(command(fr3_plan(0.1, 1.0)))
                assert done.status == "done", done.message
                threading.Timer(0.4, token.undeclare).start()
                stopped = executor.execute(command(fr3_plan(-0.3, 3.0)))
                assert stopped.status == "stopped" and "lease" in stopped.message, stopped.message
            finally:
                estop.close()
                arm.disconnect()
                hand.disconnect()


# ------------------------------------------------------------------------------------------ the bridge service
def test_the_bridge_service_routes_commands_to_its_hardware_and_refuses_other_robots(robot, planner):
    from services.robot_bridge.service import Bridge

    bridge = Bridge(robot.session)
    bridge.hardware = robot.executor  # what attach_hardware sets after connecting the devices
    try:
        wait_for_lease(robot.session)
        state = bridge.execute(command(plan(arm_goal=XARM_HOME + 0.05)))
        assert state.status == "done", state.message
        assert robot.moved()
        panda_plan = Plan(arm="panda", hand="allegro", joint_names=["a"], positions=np.zeros((2, 1)),
                          times_s=np.array([0.0, 1.0]))
        refused = bridge.execute(command(panda_plan))
        assert refused.status == "refused" and "xarm7 + leap" in refused.message
        assert not bridge._executors  # no simulated robot was built behind the hardware
    finally:
        bridge.hardware = None  # the fixture disconnects the devices
        bridge.close()


def test_the_bridge_process_names_a_missing_device_address():
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "services.robot_bridge", "--hardware", "xarm7+leap"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--xarm7-ip is required" in done.stderr
