"""The MuJoCo robot: its model, joint tracking, a push with MuJoCo's contacts, the executor's
checks on it, and its refusals of bad input."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from shared.contracts.messages import ExecutionCommand, ObjectRef, Plan, SimWorld
from shared.execution.executor import EStopLatch, Executor, LocalLease
from shared.execution.limits import SafetyRefusal
from shared.execution.robot import JointTrajectory
from shared.execution.robots.mujoco.config import MujocoConfig
from shared.execution.robots.mujoco.decompose import DecompositionError, convex_pieces, decompose_mesh
from shared.execution.robots.mujoco.model import ModelError, build_model, compile_spec, robot_spec
from shared.execution.robots.mujoco.robot import MujocoRobot
from shared.execution.robots.sim.config import limits
from shared.execution.robots.sim.robot import TrueWorld
from shared.frames import direction_frame, pose25_to_matrix, quat_xyzw_to_matrix
from shared.world.objects import load_object

mujoco = pytest.importorskip("mujoco")
torch.set_num_threads(1)

ROBOTS = [("panda", "allegro"), ("xarm7", "leap")]


def executor_for(robot: MujocoRobot) -> Executor:
    return Executor(robot.arm_name, robot.hand_name, [robot], EStopLatch(), publish=robot.publish)


def execute(executor: Executor, plan: Plan) -> object:
    return executor.execute(ExecutionCommand(plan=plan, lease_token="test", realtime_factor=1000.0), LocalLease())


def straight(robot: MujocoRobot, start: np.ndarray, goal: np.ndarray, duration_s: float, steps: int = 40) -> Plan:
    alphas = np.linspace(0.0, 1.0, steps)[:, None]
    return Plan(arm=robot.arm_name, hand=robot.hand_name, joint_names=list(robot.joint_names),
                positions=start + alphas * (goal - start), times_s=np.linspace(0.0, duration_s, steps))


# ------------------------------------------------------------------------------------------ model


@pytest.mark.parametrize("arm,hand", ROBOTS)
def test_the_model_compiles_with_a_servo_on_every_joint_of_the_arm_and_hand(arm, hand):
    model = build_model(MujocoConfig(arm, hand))
    expected = limits(arm, hand).joint_names
    assert len(expected) == 23
    assert tuple(model.actuator(i).name for i in range(model.nu)) == expected
    for name in expected:
        joint = model.joint(name)
        assert model.jnt_type[joint.id] == mujoco.mjtJoint.mjJNT_HINGE
        lower, upper = model.jnt_range[joint.id]
        k = expected.index(name)
        assert lower == pytest.approx(limits(arm, hand).lower[k], abs=1e-6)
        assert upper == pytest.approx(limits(arm, hand).upper[k], abs=1e-6)
    assert model.geom("table").type == mujoco.mjtGeom.mjGEOM_PLANE


def test_a_model_that_fails_to_compile_names_the_body_and_the_reason():
    spec = robot_spec("panda", "allegro")
    spec.compiler.balanceinertia = False  # the Allegro URDF's link_3.0 inertia breaks the triangle inequality
    with pytest.raises(ModelError, match=r"panda\+allegro.*'link_3\.0'.*inertia must satisfy"):
        compile_spec(spec, "panda+allegro")


# ------------------------------------------------------------------------------------------ bad meshes


@pytest.mark.parametrize("mesh", [
    trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0]], float) * 0.05,
                    np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3], [0, 2, 4]]), process=False),  # flat
    trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]), process=False),
], ids=["flat", "one-triangle"])
def test_a_mesh_that_cannot_be_decomposed_is_refused_with_the_objects_id(mesh):
    with pytest.raises(DecompositionError, match="object mesh-bad-001"):
        decompose_mesh("mesh-bad-001", mesh)


def test_a_concave_mesh_is_decomposed_into_convex_pieces_covering_it():
    # A U: its single convex hull would fill the notch.
    a = trimesh.creation.box((0.09, 0.03, 0.03))
    left = trimesh.creation.box((0.03, 0.03, 0.06))
    left.apply_translation((-0.03, 0.0, 0.045))
    right = left.copy()
    right.apply_translation((0.06, 0.0, 0.0))
    u = trimesh.boolean.union([a, left, right], engine="manifold")
    pieces = decompose_mesh("u-shape", u)
    assert len(pieces) >= 2
    assert sum(p.volume for p in pieces) < 0.8 * u.convex_hull.volume


def test_an_unloadable_world_is_refused_naming_the_check():
    robot = MujocoRobot(MujocoConfig("panda", "allegro"))
    with robot:
        world = SimWorld(object=ObjectRef(library_id="rnd-9999"), object_pose={"position": [0.5, 0, 0.05],
                                                                                 "quaternion_xyzw": [0, 0, 0, 1]})
        with pytest.raises(SafetyRefusal, match=r"^world: "):
            robot.reset_told(world)


# ------------------------------------------------------------------------------------------ tracking


@pytest.mark.parametrize("arm,hand", ROBOTS)
def test_a_trajectory_executes_and_the_joints_track_it(arm, hand):
    states = []
    with MujocoRobot(MujocoConfig(arm, hand), publish=states.append) as robot:
        start = robot.observe().positions.copy()
        goal = start.copy()
        goal[:7] += np.array([0.3, 0.2, -0.2, 0.3, 0.2, -0.2, 0.3])
        goal[7 + 1] += 0.6  # bend a finger
        goal[7 + 5] += 0.4
        trajectory = JointTrajectory(robot.joint_names, start + np.linspace(0, 1, 40)[:, None] * (goal - start),
                                     np.linspace(0.0, 2.0, 40))
        report = robot.send(trajectory, realtime_factor=1000.0)
    assert report.completed and report.final_joint_error < 0.005, report.message
    assert len(states) >= 0.9 * 2.3 * robot.state_rate_hz  # published at the state rate of robot time
    errors = np.array([np.abs(s.positions.to_numpy() - trajectory.sample(s.plan_time_s)) for s in states])
    assert errors[:, :7].max() < 0.02, f"arm joints lag the trajectory by {errors[:, :7].max():.4f} rad"
    assert errors[:, 7:].max() < 0.05, f"hand joints lag the trajectory by {errors[:, 7:].max():.4f} rad"


# ------------------------------------------------------------------------------------------ push + executor


@pytest.fixture(scope="module")
def push():
    return planned_box_push()


def planned_box_push():
    """The planner's push of a box 0.15 m sideways with the open Allegro hand (as the PyBullet robot's test):
    (box, plan, T_world_O, T_world_D)."""
    from shared.planning.motion import MotionPlanner
    from shared.robots.hands import load_hand
    from shared.world.fixed_poses import spatula_pose
    from shared.world.objects import write_object_urdf
    from shared.world.sim.robot_scene import RobotScene

    box = load_object("proc-box-013")  # 13.9 x 4.6 x 7.5 cm, 0.24 kg
    T_world_D = direction_frame(np.array([0.55, 0.0, 0.0]), 90.0)
    T_D_O = box.T_D_O(yaw_rad=np.pi / 2)
    T_world_O = T_world_D @ T_D_O
    hand = load_hand("allegro")
    T_D_hand, q_hand = pose25_to_matrix(spatula_pose(hand, box.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]))
    with RobotScene("panda", "allegro") as scene:
        scene.add_object(write_object_urdf(box), T_world_O)
        plan = MotionPlanner(scene).plan_push(T_world_D @ T_D_hand, q_hand, T_world_D[:3, 0], 0.15,
                                              q_hand_start=hand.open_joint_positions.numpy())
    return box, plan, T_world_O, T_world_D


def test_the_executor_runs_a_planned_push_and_the_box_moves_in_the_push_direction(push):
    box, plan, T_world_O, T_world_D = push
    with MujocoRobot(MujocoConfig("panda", "allegro")) as robot:
        robot.reset_world(TrueWorld(ObjectRef(library_id="proc-box-013"), T_world_O))
        seen_before = robot.observe().object_pose
        state = execute(executor_for(robot), plan)
        truth = robot.true_object_pose()
        collisions = dict(robot.collisions)
    assert state.status == "done", state.message
    assert truth is not None and seen_before is not None
    # What the robot reports is its tracker's, never the truth itself (the truth goes to the judge only).
    assert np.linalg.norm(np.array(seen_before.position) - T_world_O[:3, 3]) > 0.0
    assert np.linalg.norm(np.array(state.object_pose.position) - np.array(truth.position)) < 0.02
    moved = np.array(truth.position) - T_world_O[:3, 3]
    along = float(moved @ T_world_D[:3, 0])
    assert 0.07 <= along <= 0.20, f"box moved {along:.3f} m along the push"
    assert abs(float(moved @ T_world_D[:3, 1])) < 0.03
    rotation = quat_xyzw_to_matrix(np.array(truth.quaternion_xyzw)) @ T_world_O[:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))) < 20.0
    assert abs(truth.position[2] - T_world_O[2, 3]) < 0.005, "the box stays on the table"
    assert np.abs(state.positions.to_numpy() - plan.positions.to_numpy()[-1]).max() < 0.01
    assert collisions == {}, f"the robot touched something besides the box: {collisions}"


def test_the_executor_refuses_on_the_mujoco_robot_what_it_refuses_on_the_pybullet_one():
    with MujocoRobot(MujocoConfig("panda", "allegro")) as robot:
        executor = executor_for(robot)
        start = robot.observe().positions.copy()
        beyond = start.copy()
        beyond[1] = 1.9  # panda_joint2's upper limit is 1.7628 rad
        state = execute(executor, straight(robot, start, beyond, 10.0))
        assert state.status == "refused" and "panda_joint2" in state.message and "joint position" in state.message
        elsewhere = start.copy()
        elsewhere[0] += 0.3
        state = execute(executor, straight(robot, elsewhere, elsewhere + 0.01, 2.0))
        assert state.status == "refused" and state.message.startswith("start:") and "panda_joint1" in state.message
        assert np.allclose(robot.observe().positions, start, atol=1e-6), "a refused plan must not move the robot"
        xarm_plan = Plan(arm="xarm7", hand="leap", joint_names=list(limits("xarm7", "leap").joint_names),
                         positions=np.zeros((2, 23)), times_s=np.array([0.0, 1.0]))
        assert execute(executor, xarm_plan).status == "refused"


def test_a_convex_library_object_is_one_piece_its_own_hull():
    box = load_object("proc-box-013")
    pieces = convex_pieces(box)
    assert len(pieces) == 1 and pieces[0].volume == pytest.approx(box.volume, rel=0.01)


def test_a_lost_lease_stops_the_mujoco_robot_mid_motion():
    import threading

    with MujocoRobot(MujocoConfig("panda", "allegro")) as robot:
        start = robot.observe().positions.copy()
        goal = start.copy()
        goal[0] += 1.0
        lease = LocalLease()
        threading.Timer(0.3, lease.release).start()
        state = executor_for(robot).execute(
            ExecutionCommand(plan=straight(robot, start, goal, 4.0), lease_token="test", realtime_factor=1.0), lease)
    assert state.status == "stopped"
    assert 0.0 < state.positions.to_numpy()[0] - start[0] < 0.5
