"""The simulated robot bridge: refuses plans outside the limits, executes valid ones, pushes a box."""
from __future__ import annotations

import os
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import free_port, router_config
from shared.contracts.messages import CircleObstacle, ExecutionCommand, ExecutionState, Plan
from shared.execution.executor import EStopLatch, Executor, LocalLease
from shared.execution.robot import MotionStopped
from shared.execution.robots.sim.config import SimConfig
from shared.execution.robots.sim.robot import SimRobot
from shared.frames import direction_frame, pose25_to_matrix, quat_xyzw_to_matrix
from shared.planning.motion import MotionPlanner
from shared.robots.hands import load_hand
from shared.robots.robot_limits import WorkspaceBox
from shared.world.objects import load_object, write_object_urdf
from shared.world.sim.robot_scene import RobotScene

torch.set_num_threads(1)

HAND_JOINTS = 16


@pytest.fixture(scope="module")
def backend():
    robot = SimRobot(SimConfig("panda", "allegro"))
    robot.connect()
    yield robot
    robot.disconnect()


@pytest.fixture()
def executor(backend):
    backend.recover()
    backend.reset()
    return sim_executor(backend)


def sim_executor(robot: SimRobot) -> Executor:
    """The simulated robot behind the safety executor, as the evaluation runs it (publishing through the robot's hook)."""
    return Executor(robot.arm_name, robot.hand_name, [robot], EStopLatch(), publish=robot.publish)


def execute(executor: Executor, plan: Plan, realtime_factor: float = 1.0, command_id: str | None = None,
            lease: LocalLease | None = None) -> ExecutionState:
    command = ExecutionCommand(plan=plan, lease_token="test", realtime_factor=realtime_factor)
    if command_id is not None:
        command.id = command_id
    return executor.execute(command, lease or LocalLease())


def start_configuration(backend: SimRobot) -> np.ndarray:
    return backend.observe().positions.copy()


def straight_plan(start: np.ndarray, goal: np.ndarray, duration_s: float, steps: int = 50) -> Plan:
    """A plan moving every joint linearly from `start` to `goal` in `duration_s`."""
    alphas = np.linspace(0.0, 1.0, steps)[:, None]
    return Plan(arm="panda", hand="allegro", joint_names=list(SimRobot(SimConfig("panda", "allegro")).joint_names),
                positions=start + alphas * (goal - start), times_s=np.linspace(0.0, duration_s, steps))


# ---------------------------------------------------------------------------------------- refusals


def test_refuses_a_joint_beyond_its_limit(backend, executor):
    start = start_configuration(backend)
    goal = start.copy()
    goal[1] = 1.9  # panda_joint2's upper limit is 1.7628 rad
    state = execute(executor, straight_plan(start, goal, 10.0), realtime_factor=100.0)
    assert state.status == "refused"
    assert "joint position" in state.message and "panda_joint2" in state.message and "t=" in state.message
    assert np.allclose(backend.observe().positions, start, atol=1e-3), "a refused plan must not move the robot"


def test_refuses_a_plan_that_is_too_fast(backend, executor):
    start = start_configuration(backend)
    goal = start.copy()
    goal[3] += 0.5  # panda_joint4 0.5 rad in 0.1 s = 5 rad/s > 2.175 rad/s
    state = execute(executor, straight_plan(start, goal, 0.1), realtime_factor=100.0)
    assert state.status == "refused"
    assert "joint velocity" in state.message and "panda_joint4" in state.message and "rad/s" in state.message


def test_refuses_a_plan_that_leaves_the_workspace_box(backend, executor):
    start = start_configuration(backend)
    goal = start.copy()
    goal[0] += 1.0  # swings the hand ~0.28 m to the left (+y)
    executor.limits = replace(executor.limits, workspace=WorkspaceBox(lower=(-0.4, -0.2, -0.005), upper=(1.0, 0.2, 1.3)))
    state = execute(executor, straight_plan(start, goal, 10.0), realtime_factor=100.0)
    assert state.status == "refused"
    assert "workspace box" in state.message and "t=" in state.message


def test_refuses_a_plan_that_does_not_start_where_the_robot_is(backend, executor):
    start = start_configuration(backend)
    elsewhere = start.copy()
    elsewhere[0] += 0.3
    state = execute(executor, straight_plan(elsewhere, elsewhere + 0.01, 2.0), realtime_factor=100.0)
    assert state.status == "refused" and "panda_joint1" in state.message


# --------------------------------------------------------------------------------------- execution


def test_executes_a_valid_plan_and_ends_at_its_final_configuration(backend):
    states: list[ExecutionState] = []
    backend.publish = states.append
    try:
        executor = sim_executor(backend)
        backend.reset()
        start = start_configuration(backend)
        goal = start.copy()
        goal[:7] += np.array([0.3, 0.2, -0.2, 0.3, 0.2, -0.2, 0.3])
        goal[7 + 1] = 0.8  # bend the index finger
        plan = straight_plan(start, goal, 2.0)
        started = time.monotonic()
        state = execute(executor, plan, realtime_factor=4.0, command_id="valid")
        elapsed = time.monotonic() - started
    finally:
        backend.publish = None
    assert state.status == "done", state.message
    assert np.abs(state.positions.to_numpy() - goal).max() < 0.01
    assert elapsed >= (2.0 + 0.3) / 4.0 * 0.9, "paced to the realtime factor"
    executing = [s for s in states if s.status == "executing"]
    assert len(executing) >= 0.9 * 2.3 * backend.state_rate_hz  # published at the state rate of robot time
    assert states[-1].status == "done" and states[-1].command_id == "valid"


def test_stop_halts_a_running_plan(backend):
    executor = sim_executor(backend)
    backend.reset()
    start = start_configuration(backend)
    goal = start.copy()
    goal[0] += 1.0
    lease = LocalLease()
    threading.Timer(0.2, lease.release).start()
    state = execute(executor, straight_plan(start, goal, 4.0), realtime_factor=1.0, lease=lease)
    assert state.status == "stopped"
    assert 0.0 < state.positions.to_numpy()[0] - start[0] < 0.5


# ----------------------------------------------------------------------------------- push physics


def test_executing_a_planned_push_moves_the_box_in_the_push_direction():
    """The open, spatula-like hand pushes a box 0.15 m sideways with the planner's IK + RRT + Cartesian push."""
    from shared.world.fixed_poses import spatula_pose

    box = load_object("proc-box-013")  # 13.9 x 4.6 x 7.5 cm, 0.24 kg
    T_world_D = direction_frame(np.array([0.55, 0.0, 0.0]), 90.0)
    T_D_O = box.T_D_O(yaw_rad=np.pi / 2)  # long side across the push
    T_world_O = T_world_D @ T_D_O
    hand = load_hand("allegro")
    T_D_hand, q_hand = pose25_to_matrix(spatula_pose(hand, box.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]))
    urdf = write_object_urdf(box)
    with RobotScene("panda", "allegro") as scene:
        scene.add_object(urdf, T_world_O)
        plan = MotionPlanner(scene).plan_push(T_world_D @ T_D_hand, q_hand, T_world_D[:3, 0], 0.15,
                                              q_hand_start=hand.open_joint_positions.numpy())
    with SimRobot(SimConfig("panda", "allegro")) as robot:
        robot.add_object(urdf, T_world_O)
        state = execute(sim_executor(robot), plan, realtime_factor=1000.0)
        collisions = dict(robot.collisions)
        final = robot.true_object_pose()  # the physics, judged (placed without its model, nothing tracks it)
    assert state.status == "done", state.message
    assert state.object_pose is None and state.object_lost is not None
    moved = np.array(final.position) - T_world_O[:3, 3]
    along = float(moved @ T_world_D[:3, 0])
    assert 0.10 <= along <= 0.20, f"box moved {along:.3f} m along the push"
    assert np.linalg.norm(moved[:2] - along * T_world_D[:2, 0]) < 0.03
    rotation = quat_xyzw_to_matrix(np.array(final.quaternion_xyzw)) @ T_world_O[:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))) < 15.0
    assert np.abs(state.positions.to_numpy() - plan.positions.to_numpy()[-1]).max() < 0.01
    assert collisions == {}, f"the robot touched something besides the box: {collisions}"


def test_contact_with_an_obstacle_during_execution_is_recorded():
    with SimRobot(SimConfig("panda", "allegro")) as robot:
        robot.add_obstacles([CircleObstacle(x=0.45, y=-0.03, radius=0.05)])  # a 0.3 m tall cylinder in front of the hand
        start = start_configuration(robot)
        goal = start.copy()
        goal[1] += 0.9  # leans forward: the hand comes down from 0.54 m to below the cylinder's top
        state = execute(sim_executor(robot), straight_plan(start, goal, 3.0), realtime_factor=1000.0)
        collisions = dict(robot.collisions)
    assert any(other == "obstacle 0" for _, other in collisions), collisions
    assert "collisions:" in state.message and "obstacle 0" in state.message


# ------------------------------------------------------------------------------------------ bus


def test_bridge_service_executes_a_leased_command_and_publishes_states(zenoh_router):
    from services.robot_bridge.bus_safety import COMMAND_KEY, ESTOP_KEY
    from services.robot_bridge.service import SERVICE, STATE_KEY, run
    from shared.bus import BusConfig, live_workers, open_session
    from shared.bus.lease import lease_key
    from shared.contracts.codec import decode, encode
    from shared.contracts.messages import EStop, ExecutionCommand
    from shared.robots.arms import load_arm

    cfg = BusConfig(mode="client", connect=[zenoh_router], connect_timeout_ms=5000)
    stop = threading.Event()
    worker = threading.Thread(target=run, args=(cfg, "sim-bridge", stop), daemon=True)
    worker.start()
    published: list[ExecutionState] = []

    def command(session, plan: Plan, lease: str, realtime_factor: float = 20.0) -> ExecutionState:
        payload, encoding = encode(ExecutionCommand(plan=plan, lease_token=lease, realtime_factor=realtime_factor))
        replies = list(session.get(COMMAND_KEY, payload=payload, encoding=encoding, timeout=30.0))
        assert len(replies) == 1 and replies[0].ok is not None
        return decode(replies[0].ok.payload.to_bytes(), str(replies[0].ok.encoding))

    try:
        with open_session(cfg) as client:
            deadline = time.monotonic() + 20.0
            while not live_workers(client, SERVICE).get(SERVICE) and time.monotonic() < deadline:
                time.sleep(0.1)  # the command queryable is declared before the worker's liveliness token
            subscriber = client.declare_subscriber(
                STATE_KEY, lambda sample: published.append(decode(sample.payload.to_bytes(), str(sample.encoding))))
            start = np.concatenate([load_arm("panda").home.numpy(), load_hand("allegro").open_joint_positions.numpy()])
            goal = start.copy()
            goal[0] += 0.2
            plan = straight_plan(start, goal, 1.0)
            lease = lease_key("planner", "test-commander.1")
            refused = command(client, plan, lease)
            token = client.liveliness().declare_token(lease)
            done = command(client, plan, lease)
            # Losing the lease mid-motion stops the robot.
            threading.Timer(0.5, token.undeclare).start()
            lease_lost = command(client, straight_plan(goal, start, 3.0), lease, realtime_factor=1.0)
            # An e-stop stops everything and latches: the next command is refused.
            estop_payload, estop_encoding = encode(EStop(reason="test e-stop"))
            client.put(ESTOP_KEY, estop_payload, encoding=estop_encoding)
            time.sleep(0.3)
            client.liveliness().declare_token(lease)
            after_estop = command(client, straight_plan(start, start, 1.0), lease)
            subscriber.undeclare()
    finally:
        stop.set()
        worker.join(timeout=15.0)
    assert refused.status == "refused" and "lease" in refused.message  # no liveliness token at the lease yet
    assert done.status == "done", done.message
    assert np.abs(done.positions.to_numpy() - goal).max() < 0.01
    assert any(s.status == "executing" for s in published) and done.command_id in {s.command_id for s in published}
    assert lease_lost.status == "stopped" and "lease" in lease_lost.message
    assert after_estop.status == "refused" and "e-stop" in after_estop.message


# ------------------------------------------------------------------------ the bridge's lease and e-stop
# A Bridge (the bus adapter) with its simulated robot on a router, a commander holding a planner lease,
# and a 3 s move of joint 0 by 0.8 rad started from the robot's home. Stop latency is measured from the
# fault (lease undeclared, router closed or hung, e-stop published) to the moment the simulated robot's
# execute() raised MotionStopped.
MOVE_RAD = 0.8
STOP_BOUND_S = 0.5  # the target is 0.2 s; slack for a loaded 2-core CI machine


def bus_session(endpoint: str):
    from shared.bus import BusConfig, open_session

    return open_session(BusConfig(mode="client", connect=[endpoint], connect_timeout_ms=5000))


def home_configuration() -> np.ndarray:
    from shared.robots.arms import load_arm

    return np.concatenate([load_arm("panda").home.numpy(), load_hand("allegro").open_joint_positions.numpy()])


def box_world():
    from shared.contracts.messages import ObjectPose, ObjectRef, SimWorld

    return SimWorld(object=ObjectRef(library_id="proc-box-013"), object_pose=ObjectPose(position=(0.35, -0.45, 0.04)))


class BusBridge:
    """A Bridge on `endpoint` (with a router watchdog if asked: what `service.run` builds), its simulated robot
    built, and a commander session."""

    def __init__(self, endpoint: str, watchdog: bool = False, confirm_timeout_s: float | None = None,
                 robot: str = "sim"):
        from services.robot_bridge.service import Bridge

        self.session, self.commander = bus_session(endpoint), bus_session(endpoint)
        self.probe = bus_session(endpoint) if watchdog else None
        self.bridge = Bridge(self.session, probe=self.probe, confirm_timeout_s=confirm_timeout_s, robot=robot)
        self.backend = self.bridge.executor("panda", "allegro").executor.robots[0]
        self.stopped_at: list[float] = []
        send = self.backend.send

        def timed_send(*args, **kwargs):
            try:
                return send(*args, **kwargs)
            except MotionStopped:
                self.stopped_at.append(time.monotonic())
                raise

        self.backend.send = timed_send

    def lease(self, holder: str) -> tuple[str, object]:
        from shared.bus.lease import lease_key

        key = lease_key("planner", holder)
        return key, self.commander.liveliness().declare_token(key)

    def move(self, lease: str, world=None, duration_s: float = 3.0):
        from shared.contracts.messages import ExecutionCommand

        start = home_configuration()
        if world is None:
            self.backend.recover()
            self.backend.reset()
        goal = start.copy()
        goal[0] += MOVE_RAD
        return ExecutionCommand(plan=straight_plan(start, goal, duration_s), lease_token=lease, realtime_factor=1.0,
                                world=world)

    def run_with_fault(self, command, fault, after_s: float) -> tuple[ExecutionState, float]:
        """Execute `command` and call `fault()` `after_s` seconds after handing it over; (final state, fault time)."""
        fault_at: list[float] = []

        def inject() -> None:
            fault_at.append(time.monotonic())
            fault()

        timer = threading.Timer(after_s, inject)
        timer.start()
        try:
            state = self.bridge.execute(command)
        finally:
            timer.join()
        return state, fault_at[0]

    def travel(self, state: ExecutionState) -> float:
        return float(state.positions.to_numpy()[0] - home_configuration()[0])

    def close(self) -> None:
        self.bridge.close()
        for session in (self.commander, self.probe, self.session):
            if session is not None and not session.is_closed():
                session.close()


@pytest.fixture()
def bus_bridge(zenoh_router):
    bridge = BusBridge(zenoh_router)
    yield bridge
    bridge.close()


def test_a_lease_lost_mid_motion_stops_it_and_the_state_names_the_loss(bus_bridge):
    key, token = bus_bridge.lease("planner-1.cmd-1")
    state, fault_at = bus_bridge.run_with_fault(bus_bridge.move(key), token.undeclare, after_s=1.0)
    latency = bus_bridge.stopped_at[0] - fault_at
    print(f"lease undeclared -> sim robot halted: {latency * 1000:.0f} ms")
    assert state.status == "stopped", state.message
    assert f"lease {key!r} lost" in state.message and "token was deleted" in state.message
    assert "s after the loss was noticed" in state.message
    assert latency <= STOP_BOUND_S
    assert bus_bridge.travel(state) < 0.6 * MOVE_RAD


def test_a_command_with_a_world_runs_to_the_end_under_the_router_watchdog(zenoh_router):
    """The world reset holds Python's GIL ~0.3 s (PyBullet): the watchdog must not take that for a silent router."""
    bridge = BusBridge(zenoh_router, watchdog=True)
    try:
        key, _token = bridge.lease("planner-1.cmd-0")
        states = [bridge.bridge.execute(bridge.move(key, world=box_world(), duration_s=0.5)) for _ in range(2)]
    finally:
        bridge.close()
    assert [s.status for s in states] == ["done", "done"], [s.message for s in states]
    assert abs(bridge.travel(states[-1]) - MOVE_RAD) < 0.01


def test_the_bridge_resets_the_world_and_executes_on_the_mujoco_robot_when_asked(zenoh_router):
    """`--robot mujoco`: the same commands, leases and checks, executed by MuJoCo's robot."""
    from shared.execution.robots.mujoco.robot import MujocoRobot

    bridge = BusBridge(zenoh_router, robot="mujoco")
    try:
        assert isinstance(bridge.backend, MujocoRobot)
        key, _token = bridge.lease("planner-1.cmd-m")
        state = bridge.bridge.execute(bridge.move(key, world=box_world(), duration_s=1.0))
        truth = bridge.backend.true_object_pose()
    finally:
        bridge.close()
    assert state.status == "done", state.message
    assert abs(bridge.travel(state) - MOVE_RAD) < 0.01
    assert truth is not None and np.allclose(truth.position[:2], (0.35, -0.45), atol=2e-3)  # the command's world


def test_the_robot_flag_reaches_the_bridge_and_is_refused_with_hardware(monkeypatch, capsys, tmp_path):
    from deploy.launcher import Launcher, LaunchError
    from services.robot_bridge import __main__ as bridge_main

    calls: list[dict] = []
    monkeypatch.setattr(bridge_main, "run", lambda *args, **kwargs: calls.append(kwargs))
    monkeypatch.setattr(bridge_main, "configure_service_logging", lambda: None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    assert bridge_main.main([]) == 0 and calls[-1]["robot"] == "sim"
    assert bridge_main.main(["--robot", "mujoco"]) == 0 and calls[-1]["robot"] == "mujoco"
    assert os.environ["MUJOCO_GL"] == "egl"  # the service renders headless unless told otherwise
    with pytest.raises(SystemExit):
        bridge_main.main(["--robot", "mujoco", "--hardware", "xarm7+leap", "--xarm7-ip", "10.0.0.2",
                          "--leap-port", "/dev/null"])
    assert "--robot mujoco chooses the simulated robot's engine" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bridge_main.main(["--robot", "gazebo"])
    assert "invalid choice: 'gazebo'" in capsys.readouterr().err
    launcher = Launcher(validators=0, record_dir=tmp_path, log_dir=tmp_path, robot="mujoco")
    command = launcher._command("robot_bridge", "robot_bridge-1")
    assert command[command.index("--robot") + 1] == "mujoco" and command[-1] == "--no-confirm"
    assert "--robot" not in launcher._command("planner", "planner-1")
    with pytest.raises(LaunchError, match="unknown simulated robot 'gazebo'"):
        Launcher(validators=0, record_dir=tmp_path, log_dir=tmp_path, robot="gazebo")


def test_gd2p_up_help_says_what_robot_does(capsys):
    from cli.main import main

    with pytest.raises(SystemExit):
        main(["up", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--robot {sim,mujoco}" in out and "MuJoCo" in out


@pytest.mark.parametrize("key_kind", ["client lease", "a worker's liveliness token", "old-style lease",
                                      "wildcard", "too deep"])
def test_only_a_planner_lease_may_command_motion(bus_bridge, key_kind):
    from shared.bus.keys import alive_key

    key = {"client lease": "gd2p/lease/client/cli/c-1", "a worker's liveliness token": alive_key("recorder", "rec-1"),
           "old-style lease": "gd2p/lease/planner-1", "wildcard": "gd2p/lease/planner/*",
           "too deep": "gd2p/lease/planner/planner/a/b"}[key_kind]
    token = bus_bridge.commander.liveliness().declare_token(key)  # a live token is there: still not a lease
    try:
        state = bus_bridge.bridge.execute(bus_bridge.move(key))
    finally:
        token.undeclare()
    assert state.status == "refused" and state.message.startswith("lease:"), state.message
    assert "gd2p/lease/planner/<identity>/<holder>" in state.message
    assert abs(bus_bridge.travel(state)) < 1e-3


def test_a_command_heard_again_is_refused_and_nothing_moves(bus_bridge):
    """A replayed command (the same id) runs at most once, even after the arm went back to where it started."""
    key, _token = bus_bridge.lease("planner-1.cmd-replay")
    command = bus_bridge.move(key, duration_s=1.0)
    first = bus_bridge.bridge.execute(command)
    assert first.status == "done", first.message
    bus_bridge.backend.reset()  # the arm is back at the plan's start: only the id can tell the replay apart
    again = bus_bridge.bridge.execute(command)
    assert again.status == "refused" and again.message.startswith("replay:"), again.message
    assert command.id in again.message
    assert abs(bus_bridge.travel(again)) < 1e-3


def test_a_lease_lost_during_the_world_reset_refuses_the_command(bus_bridge, monkeypatch):
    key, token = bus_bridge.lease("planner-1.cmd-2")
    reset_world = SimRobot.reset_world

    def reset_and_lose_the_lease(robot, world):
        reset_world(robot, world)
        token.undeclare()  # the commander gives up while the world is being reset
        time.sleep(0.1)

    monkeypatch.setattr(SimRobot, "reset_world", reset_and_lose_the_lease)
    state = bus_bridge.bridge.execute(bus_bridge.move(key, world=box_world()))
    assert state.status == "refused" and "lease" in state.message and "lost" in state.message, state.message
    assert abs(bus_bridge.travel(state)) < 0.01


@pytest.mark.parametrize("drop_after_s", [0.05, 0.15, 0.25])
def test_a_lease_dropped_right_after_sending_never_lets_the_motion_complete(bus_bridge, drop_after_s):
    """The issue's measurement: the commander drops its lease 0.05-0.25 s after sending a command with a world."""
    key, token = bus_bridge.lease(f"planner-1.drop-{int(drop_after_s * 1000)}")
    state, _ = bus_bridge.run_with_fault(bus_bridge.move(key, world=box_world()), token.undeclare, drop_after_s)
    assert state.status in {"refused", "stopped"} and "lease" in state.message, state.message
    assert bus_bridge.travel(state) < 0.25 * MOVE_RAD


def _router(endpoint: str):
    import zenoh


    return zenoh.open(router_config(endpoint))


def test_the_motion_stops_when_the_bridge_loses_its_router():

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = _router(endpoint)
    bridge = BusBridge(endpoint)
    try:
        key, _token = bridge.lease("planner-1.cmd-3")
        state, fault_at = bridge.run_with_fault(bridge.move(key), router.close, after_s=1.0)
        latency = bridge.stopped_at[0] - fault_at
        print(f"router closed -> sim robot halted: {latency * 1000:.0f} ms")
    finally:
        bridge.close()
        if not router.is_closed():
            router.close()
    assert state.status == "stopped" and f"lease {key!r} lost" in state.message, state.message
    assert latency <= STOP_BOUND_S
    assert bridge.travel(state) < 0.6 * MOVE_RAD


def test_the_motion_stops_when_the_router_hangs():
    """A router that stops answering without closing its links (SIGSTOP): only the router watchdog notices."""
    import os
    import signal
    import subprocess
    import sys


    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code = ("import sys, time; from conftest import router_config; import zenoh; "
            f"s = zenoh.open(router_config({endpoint!r})); print('up', flush=True); time.sleep(120)")
    router = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.abspath(__file__)))
    bridge = None
    try:
        assert router.stdout.readline().strip() == "up"
        bridge = BusBridge(endpoint, watchdog=True)
        key, _token = bridge.lease("planner-1.cmd-4")
        state, fault_at = bridge.run_with_fault(bridge.move(key), lambda: router.send_signal(signal.SIGSTOP),
                                                after_s=1.0)
        latency = bridge.stopped_at[0] - fault_at
        print(f"router hung -> sim robot halted: {latency * 1000:.0f} ms")
    finally:
        router.send_signal(signal.SIGCONT)
        router.kill()
        router.wait(timeout=10)
        if bridge is not None:
            bridge.close()
    assert state.status == "stopped" and "router forwarded nothing" in state.message, state.message
    assert latency <= STOP_BOUND_S
    assert bridge.travel(state) < 0.6 * MOVE_RAD


@pytest.mark.parametrize("kind", ["empty", "garbage", "wrong encoding", "ErrorReply", "Plan", "valid EStop"])
def test_anything_on_the_estop_key_stops_the_simulated_robot_and_latches(bus_bridge, kind):
    from services.robot_bridge.bus_safety import ESTOP_KEY
    from shared.contracts.codec import encode
    from shared.contracts.messages import ErrorReply, EStop

    payload, encoding = {
        "empty": (b"", None),
        "garbage": (b"\xff\x00garbage", "application/msgpack;EStop"),
        "wrong encoding": (b"STOP", "text/plain"),
        "ErrorReply": encode(ErrorReply(code="internal", message="not a stop")),
        "Plan": encode(straight_plan(home_configuration(), home_configuration(), 1.0)),
        "valid EStop": encode(EStop(reason="person in the cell", issued_by="operator")),
    }[kind]
    key, _token = bus_bridge.lease("planner-1.cmd-5")
    sender = bus_bridge.commander
    state, fault_at = bus_bridge.run_with_fault(
        bus_bridge.move(key), lambda: sender.put(ESTOP_KEY, payload, encoding=encoding), after_s=1.0)
    latency = bus_bridge.stopped_at[0] - fault_at
    print(f"e-stop ({kind}) -> sim robot halted: {latency * 1000:.0f} ms")
    assert state.status == "stopped" and state.message.startswith("e-stop: "), state.message
    assert latency <= STOP_BOUND_S
    assert bus_bridge.bridge.estop_latch.triggered.is_set()
    refused = bus_bridge.bridge.execute(bus_bridge.move(key))
    assert refused.status == "refused" and "e-stop is latched" in refused.message
